//! What puts the carriage and the follower at a station of the pose plan (DESIGN §3: the
//! poses cover the follower window along the travel, so the procedure visits several
//! positions). The procedure asks for each station before its first pose, and again after a
//! resume, and waits until both are there. The service moves the twin's carriage through
//! the twin's CNC and the follower through its own drive (`service::hexapod_run`); where
//! nothing can move them (`Stay`), a plan at several positions is refused before any move.

use std::future::Future;

/// Moves the carriage (travel, mm) and the follower (mm) to a station and returns once both
/// are at rest there; `Err` says why not, in words.
pub trait Bench: Send {
    /// Whether this bench can move at all (else only one-station plans run).
    fn moves(&self) -> bool;

    fn go_to(
        &mut self,
        travel_mm: f64,
        follower_mm: f64,
    ) -> impl Future<Output = Result<(), String>> + Send;
}

/// The carriage and the follower stay where the operator put them.
#[derive(Clone, Copy, Debug, Default)]
pub struct Stay;

impl Bench for Stay {
    fn moves(&self) -> bool {
        false
    }

    async fn go_to(&mut self, _travel_mm: f64, _follower_mm: f64) -> Result<(), String> {
        Ok(())
    }
}
