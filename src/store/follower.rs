//! Follower error maps (`follower::FollowerMap`): stored whole as TOML with their source and
//! date, with the certificate they were built from (a later self-calibration combines with
//! it) and the self-calibration's steps (a level's stations, or a newer fit, fit them again;
//! `follower::StoredMap`); at most one is in use (the tracker applies it).

use super::{Store, StoreError, now_us};
use crate::follower::{Certificate, FollowerMap, Source, StoredMap, StoredSteps};
use rusqlite::{OptionalExtension, params};

/// A stored follower map.
#[derive(Clone, Debug, PartialEq)]
pub struct FollowerMapRecord {
    pub id: i64,
    pub created_us: i64,
    /// `certificate`, `self-calibration` or `both`.
    pub source: String,
    /// The certificate's file, or how the map was made.
    pub name: String,
    pub in_use: bool,
    pub map: FollowerMap,
    /// The certificate the map was built from (none for maps stored before it was kept).
    pub certificate: Option<Certificate>,
    /// The self-calibration's steps and its fit's settings (none for a map from a
    /// certificate alone, or stored before the steps were kept: it cannot be fitted again).
    pub steps: Option<StoredSteps>,
}

/// What a map is made from, as the store names it.
pub fn source_of(map: &FollowerMap) -> &'static str {
    let cert = map.sources.long == Source::Certificate;
    let own = map.sources.vertical == Source::SelfCalibration;
    match (cert, own) {
        (true, true) => "both",
        (true, false) => "certificate",
        _ => "self-calibration",
    }
}

impl Store {
    /// Store a follower map named `name`; with `use_it` it becomes the map in use.
    pub fn insert_follower_map(
        &mut self,
        map: &FollowerMap,
        name: &str,
        use_it: bool,
    ) -> Result<i64, StoreError> {
        self.insert_follower_map_with(map, None, name, use_it)
    }

    /// Store a follower map and the certificate it was built from, named `name`; with
    /// `use_it` it becomes the map in use.
    pub fn insert_follower_map_with(
        &mut self,
        map: &FollowerMap,
        certificate: Option<&Certificate>,
        name: &str,
        use_it: bool,
    ) -> Result<i64, StoreError> {
        let stored = StoredMap {
            map: map.clone(),
            certificate: certificate.cloned(),
            steps: None,
        };
        self.insert_stored_follower_map(&stored, name, use_it)
    }

    /// Store a follower map with its certificate and its self-calibration's steps
    /// (`follower::StoredMap`), named `name`; with `use_it` it becomes the map in use.
    pub fn insert_stored_follower_map(
        &mut self,
        stored: &StoredMap,
        name: &str,
        use_it: bool,
    ) -> Result<i64, StoreError> {
        let what = "store a follower map";
        let label = self.label();
        let fail = |e| super::classify(&label, what, e);
        let tx = self.conn.transaction().map_err(fail)?;
        if use_it {
            tx.execute("UPDATE follower_maps SET in_use = 0 WHERE in_use = 1", [])
                .map_err(fail)?;
        }
        tx.execute(
            "INSERT INTO follower_maps (created_us, source, name, map_toml, in_use) \
             VALUES (?1, ?2, ?3, ?4, ?5)",
            params![
                now_us(),
                source_of(&stored.map),
                name,
                stored.to_toml(),
                use_it as i64
            ],
        )
        .map_err(fail)?;
        let id = tx.last_insert_rowid();
        tx.commit().map_err(fail)?;
        Ok(id)
    }

    /// Put stored map `id` in use (and no other).
    pub fn use_follower_map(&mut self, id: i64) -> Result<(), StoreError> {
        let what = "choose the follower map in use";
        let label = self.label();
        let fail = |e| super::classify(&label, what, e);
        let tx = self.conn.transaction().map_err(fail)?;
        tx.execute("UPDATE follower_maps SET in_use = 0 WHERE in_use = 1", [])
            .map_err(fail)?;
        let n = tx
            .execute("UPDATE follower_maps SET in_use = 1 WHERE id = ?1", [id])
            .map_err(fail)?;
        if n == 0 {
            return Err(StoreError::NoSuchFollowerMap(id));
        }
        tx.commit().map_err(fail)
    }

    /// Every stored follower map, oldest first.
    pub fn follower_maps(&self) -> Result<Vec<FollowerMapRecord>, StoreError> {
        self.query_follower_maps(
            "SELECT id, created_us, source, name, in_use, map_toml FROM follower_maps ORDER BY id",
        )
    }

    /// The follower map in use, if any.
    pub fn follower_map_in_use(&self) -> Result<Option<FollowerMapRecord>, StoreError> {
        Ok(self
            .query_follower_maps(
                "SELECT id, created_us, source, name, in_use, map_toml FROM follower_maps WHERE in_use = 1",
            )?
            .pop())
    }

    /// Stored map `id`.
    pub fn follower_map(&self, id: i64) -> Result<FollowerMapRecord, StoreError> {
        let what = "read a follower map";
        let found = self
            .conn
            .query_row("SELECT id FROM follower_maps WHERE id = ?1", [id], |r| {
                r.get::<_, i64>(0)
            })
            .optional()
            .map_err(|e| self.fail(what, e))?;
        if found.is_none() {
            return Err(StoreError::NoSuchFollowerMap(id));
        }
        self.follower_maps()?
            .into_iter()
            .find(|m| m.id == id)
            .ok_or(StoreError::NoSuchFollowerMap(id))
    }

    fn query_follower_maps(&self, sql: &str) -> Result<Vec<FollowerMapRecord>, StoreError> {
        let what = "read follower maps";
        type Raw = (i64, i64, String, String, i64, String);
        let mut stmt = self.conn.prepare(sql).map_err(|e| self.fail(what, e))?;
        let raws: Vec<Raw> = stmt
            .query_map([], |r| {
                Ok((
                    r.get(0)?,
                    r.get(1)?,
                    r.get(2)?,
                    r.get(3)?,
                    r.get(4)?,
                    r.get(5)?,
                ))
            })
            .and_then(|rows| rows.collect())
            .map_err(|e| self.fail(what, e))?;
        raws.into_iter()
            .map(|(id, created_us, source, name, in_use, text)| {
                let s = StoredMap::from_toml(&text, &format!("follower map {id}"))
                    .map_err(|e| self.decode(what, e))?;
                Ok(FollowerMapRecord {
                    id,
                    created_us,
                    source,
                    name,
                    in_use: in_use == 1,
                    map: s.map,
                    certificate: s.certificate,
                    steps: s.steps,
                })
            })
            .collect()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::follower::{Certificate, MapSettings, build};

    #[test]
    fn maps_round_trip_and_one_is_in_use() {
        let dir = std::env::temp_dir().join(format!("axiscomp-fmap-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        std::fs::create_dir_all(&dir).unwrap();
        let mut store = Store::open(dir.join("s.sqlite")).unwrap();
        let cert = Certificate::parse(
            "position_mm,error_um,direction,uncertainty_um\n0,0,+,0.2\n10,1.5,+,0.2\n",
            "c.csv",
        )
        .unwrap();
        let map = build(&[], Some(&cert), &MapSettings::default()).unwrap();
        let a = store
            .insert_follower_map_with(&map, Some(&cert), "c.csv", true)
            .unwrap();
        let b = store.insert_follower_map(&map, "c2.csv", true).unwrap();
        let in_use = store.follower_map_in_use().unwrap().unwrap();
        assert_eq!((in_use.id, in_use.source.as_str()), (b, "certificate"));
        assert_eq!((&in_use.map, &in_use.certificate), (&map, &None));
        assert_eq!(store.follower_map(a).unwrap().certificate, Some(cert));
        store.use_follower_map(a).unwrap();
        assert_eq!(store.follower_map_in_use().unwrap().unwrap().id, a);
        assert_eq!(store.follower_maps().unwrap().len(), 2);
        assert!(matches!(
            store.use_follower_map(99),
            Err(StoreError::NoSuchFollowerMap(99))
        ));
        assert_eq!(
            store.follower_map_in_use().unwrap().unwrap().id,
            a,
            "unchanged"
        );
        let _ = std::fs::remove_dir_all(&dir);
    }
}
