//! What the tracker needs from a map of the follower stage's own errors (DESIGN §4): the
//! correction at an encoder position after a motion in a direction, and the variance of the
//! difference of two corrections. The follower map (`follower::FollowerMap`) is one; the
//! tracker knows only this trait, so the map sits above the tracker and not beside it.

use crate::run::Direction;
use std::any::Any;
use std::fmt;
use std::sync::Arc;

/// A map of the follower stage's own errors, as the tracker applies it to displacements taken
/// from the encoder.
pub trait StageCorrection: fmt::Debug + Send + Sync + 'static {
    /// PSD2's true position minus the encoder's (mm: along the follower's axis, vertical) at
    /// encoder position `x` after a motion in `dir`. Only differences between two positions
    /// mean anything (the tracker uses them so).
    fn correction(&self, x: f64, dir: Direction) -> [f64; 2];

    /// Variance (mm²: along, vertical) of the correction's difference between encoder
    /// positions `a` and `b`.
    fn difference_variance(&self, a: f64, b: f64, dir_a: Direction, dir_b: Direction) -> [f64; 2];

    /// What the stage repeats to along its axis beyond the map at one position (mm, standard
    /// deviation), when the map knows it from its own data; `None`: the tracker's settings
    /// state it (`mapped_sd_mm`).
    fn unmapped_sd(&self) -> Option<f64> {
        None
    }
}

/// A map as the tracker holds it: what it calls, and the map as it was given, so whoever put
/// it in use gets it back as its own type ([`Applied::get`]).
#[derive(Clone)]
pub(super) struct Applied {
    correction: Arc<dyn StageCorrection>,
    /// The `Arc<M>` that was given.
    given: Arc<dyn Any + Send + Sync>,
}

impl Applied {
    pub(super) fn new<M: StageCorrection>(map: Arc<M>) -> Self {
        Applied {
            given: Arc::new(map.clone()),
            correction: map,
        }
    }

    /// The map, when it was given as an `Arc<M>`.
    pub(super) fn get<M: StageCorrection>(&self) -> Option<&Arc<M>> {
        self.given.downcast_ref()
    }
}

impl std::ops::Deref for Applied {
    type Target = dyn StageCorrection;
    fn deref(&self) -> &Self::Target {
        &*self.correction
    }
}

impl fmt::Debug for Applied {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        self.correction.fmt(f)
    }
}
