//! The real-time tier: what only the real clock can show, on the runtime flavour production
//! uses — the kernel's receive stamps and a link's latency, the service as a real process
//! killed and restarted, its store locked by another process. Not part of plain `cargo test` (`test = false` in Cargo.toml):
//! `.ci/run` runs it with `cargo test --test realtime`. Everything else runs on a simulated
//! clock in `tests/it`.

#[allow(dead_code)]
#[path = "../it/helpers.rs"]
mod helpers;

mod links;
mod resume;
mod serve;
mod store_lock;
