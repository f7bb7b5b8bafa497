//! The follower error map in the service: the map in use is loaded from the store at start
//! and applied to the tracker; the control API shows it (`follower_map`) or puts another
//! stored map in use (`follower_map` with `id`, operators only); the snapshot names it.

use crate::follower::{FollowerMap, Sources};
use crate::store::{FollowerMapRecord, Store};
use crate::track::Tracker;
use serde::{Deserialize, Serialize};
use std::sync::Arc;

/// The map in use, as the snapshot shows it.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct FollowerMapView {
    pub id: i64,
    pub name: String,
    /// `certificate`, `self-calibration` or `both`.
    pub source: String,
    /// When it was stored (RFC 3339, UTC).
    pub created: String,
    /// Where each term comes from.
    pub sources: Sources,
}

fn view(r: &FollowerMapRecord) -> FollowerMapView {
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
