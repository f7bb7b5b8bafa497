//! The live service (DESIGN §5, §8): tasks wired around a `Snapshot` on a watch channel.

pub mod control;
pub mod measure;
pub mod notify;
pub mod peer;
pub mod shutdown;
pub mod snapshot;
