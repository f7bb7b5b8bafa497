//! The follower error map in the service: the map in use is loaded from the store at start
//! and applied to the tracker; the control API shows it (`follower_map`), puts another
//! stored map in use (`follower_map` with `id`, operators only) or imports the encoder's
//! certificate (`follower_certificate`: stored and applied at once, joined with the
//! self-calibration of the map in use when it has one); the snapshot names it. The
//! stop-and-go self-calibration itself is `follower_map` (the module beside this one).

use super::api::{CertificateImport, FollowerMapView};
use crate::follower::{Certificate, MapSettings, StoredMap};
use crate::store::{FollowerMapRecord, Store};

pub(super) fn view(r: &FollowerMapRecord) -> FollowerMapView {
    FollowerMapView {
        id: r.id,
        name: r.name.clone(),
        source: r.source.clone(),
        created: crate::util::time::rfc3339(r.created_us.div_euclid(1_000_000)),
        sources: r.map.sources,
    }
}

/// `follower_map`, on the store's thread: with `id`, put stored map `id` in use (the tracker
/// applies it from now on; take the zero again); the answer (the map in use, its terms and the
/// stored maps), and the map now in use when it changed.
pub(super) fn request_on(
    store: &mut Store,
    id: Option<i64>,
) -> Result<(serde_json::Value, Option<FollowerMapRecord>), String> {
    let mut changed = None;
    if let Some(id) = id {
        store.use_follower_map(id).map_err(|e| e.to_string())?;
        changed = Some(store.follower_map(id).map_err(|e| e.to_string())?);
    }
    let maps = store.follower_maps().map_err(|e| e.to_string())?;
    let list: Vec<serde_json::Value> = maps
        .iter()
        .map(|m| {
            serde_json::json!({
                "id": m.id,
                "in_use": m.in_use,
                "source": m.source,
                "name": m.name,
                "created": crate::util::time::rfc3339(m.created_us.div_euclid(1_000_000)),
            })
        })
        .collect();
    let in_use = maps.iter().find(|m| m.in_use);
    Ok((
        serde_json::json!({
            "in_use": in_use.map(view),
            "summary": in_use.map(|m| m.map.summary()),
            "maps": list,
        }),
        changed,
    ))
}

/// The map a certificate makes in `store`: joined with the self-calibration of the map in
/// use when it has one (its periodic term, reversal and vertical kept, the certificate's long
/// shape in place of any other, its steps kept with it), else the certificate's alone; its
/// name, and the map it joined.
pub fn certificate_map(
    store: &Store,
    cert: &Certificate,
) -> Result<(StoredMap, String, Option<i64>), String> {
    let in_use = store.follower_map_in_use().map_err(|e| e.to_string())?;
    Ok(match in_use.filter(|r| r.map.self_calibration.is_some()) {
        Some(r) => (
            StoredMap {
                map: r.map.with_certificate(cert),
                certificate: Some(cert.clone()),
                steps: r.steps,
            },
            format!("{} with the self-calibration of map {}", cert.name, r.id),
            Some(r.id),
        ),
        None => (
            StoredMap {
                map: crate::follower::build(&[], Some(cert), &MapSettings::default())
                    .map_err(|e| e.to_string())?,
                certificate: Some(cert.clone()),
                steps: None,
            },
            cert.name.clone(),
            None,
        ),
    })
}

/// Read and parse the certificate `path` on the service's host; errors name the file and,
/// for a bad row, the line.
pub(super) fn read_certificate(path: &str) -> Result<Certificate, String> {
    let text = std::fs::read_to_string(path).map_err(|e| {
        format!("certificate {path}: cannot read it ({e}); give a CSV on the service's host")
    })?;
    Certificate::parse(&text, path).map_err(|e| e.to_string())
}

/// `follower_certificate`, on the store's thread: parse the certificate (a file is read
/// there too), make it a map ([`certificate_map`]), store it with its points; the answer, and
/// the map to put in use unless `keep_current`.
pub(super) fn import_on(
    store: &mut Store,
    req: CertificateImport,
) -> Result<(serde_json::Value, Option<FollowerMapRecord>), String> {
    let cert = match (&req.csv, &req.path) {
        (Some(text), _) => {
            let name = req.name.clone().unwrap_or_else(|| "certificate".into());
            Certificate::parse(text, &name).map_err(|e| e.to_string())?
        }
        (None, Some(path)) => {
            let mut c = read_certificate(path)?;
            if let Some(n) = &req.name {
                c.name = n.clone();
            }
            c
        }
        (None, None) => {
            return Err("follower_certificate needs \"path\" (a CSV on the service's host) or \"csv\" (its text)".into());
        }
    };
    let (stored, name, joined) = certificate_map(store, &cert)?;
    let use_it = !req.keep_current;
    let id = store
        .insert_stored_follower_map(&stored, &name, use_it)
        .map_err(|e| format!("the certificate's map was not stored: {e}"))?;
    let map = stored.map;
    let mut now_in_use = None;
    if use_it {
        now_in_use = Some(store.follower_map(id).map_err(|e| e.to_string())?);
        tracing::info!(id, %name, "follower map from a certificate in use");
    }
    let answer = serde_json::json!({
        "id": id,
        "name": name,
        "in_use": use_it,
        "joined_with": joined,
        "summary": map.summary(),
        "zero": if use_it { "the map applies from now on: take the zero again before measuring" } else { "stored; the map in use is unchanged" },
    });
    Ok((answer, now_in_use))
}
