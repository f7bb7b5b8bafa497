//! The follower error map in the service: the map in use is loaded from the store at start
//! and applied to the tracker; the control API shows it (`follower_map`), puts another
//! stored map in use (`follower_map` with `id`, operators only) or imports the encoder's
//! certificate (`follower_certificate`: stored and applied at once, joined with the
//! self-calibration of the map in use when it has one); the snapshot names it. The
//! stop-and-go self-calibration itself is `follower_map` (the module beside this one).

use super::api::{CertificateImport, FollowerMapView};
use crate::follower::{Certificate, FollowerMap, MapSettings, StoredMap};
use crate::store::{FollowerMapRecord, Store};
use crate::track::Tracker;
use std::sync::Arc;

pub(super) fn view(r: &FollowerMapRecord) -> FollowerMapView {
    FollowerMapView {
        id: r.id,
        name: r.name.clone(),
        source: r.source.clone(),
        created: crate::util::time::rfc3339(r.created_us.div_euclid(1_000_000)),
        sources: r.map.sources,
    }
}

/// The map in use in `store`, for the tracker and the snapshot (none when the store has
/// none, or cannot say: logged).
pub(super) fn in_use(store: &Store) -> (Option<FollowerMapView>, Option<Arc<FollowerMap>>) {
    match store.follower_map_in_use() {
        Ok(Some(r)) => {
            tracing::info!(id = r.id, name = %r.name, "follower map in use");
            (Some(view(&r)), Some(Arc::new(r.map)))
        }
        Ok(None) => (None, None),
        Err(e) => {
            tracing::warn!("the follower map in use could not be read: {e}; tracking without");
            (None, None)
        }
    }
}

/// `follower_map`: with `id`, put stored map `id` in use (the tracker applies it from now on;
/// take the zero again); then the map in use, its terms and the stored maps.
pub(super) fn request(
    store: &mut Store,
    tracker: &mut Tracker,
    shown: &mut Option<FollowerMapView>,
    id: Option<i64>,
) -> Result<serde_json::Value, String> {
    if let Some(id) = id {
        store.use_follower_map(id).map_err(|e| e.to_string())?;
        let r = store.follower_map(id).map_err(|e| e.to_string())?;
        tracker.set_map(Some(Arc::new(r.map.clone())));
        *shown = Some(view(&r));
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
    Ok(serde_json::json!({
        "in_use": in_use.map(view),
        "summary": in_use.map(|m| m.map.summary()),
        "maps": list,
    }))
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

/// `follower_certificate`: parse the certificate, make it a map ([`certificate_map`]), store
/// it with its points and, unless `keep_current`, put it in use in the tracker at once.
pub(super) fn import_certificate(
    store: &mut Store,
    tracker: &mut Tracker,
    shown: &mut Option<FollowerMapView>,
    req: CertificateImport,
) -> Result<serde_json::Value, String> {
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
    if use_it {
        let r = store.follower_map(id).map_err(|e| e.to_string())?;
        tracker.set_map(Some(Arc::new(r.map.clone())));
        *shown = Some(view(&r));
        tracing::info!(id, %name, "follower map from a certificate in use");
    }
    Ok(serde_json::json!({
        "id": id,
        "name": name,
        "in_use": use_it,
        "joined_with": joined,
        "summary": map.summary(),
        "zero": if use_it { "the map applies from now on: take the zero again before measuring" } else { "stored; the map in use is unchanged" },
    }))
}
