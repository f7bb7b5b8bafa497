//! The optical head as data and the forward model: layout (elements, modules, paths), skew-ray
//! tracing with homogeneous transforms, installation errors, and `(errors, D, d) → readings`.
//!
//! Scope: geometric optics with ideal thin elements (no refraction or plate shift), an ideal
//! corner cube, polarisation as a label. That is the model the decoupling inverts; the digital
//! twin perturbs it (installation errors, gains, noise) rather than adding physics.

pub mod geometry;
pub mod install;
pub mod layout;
pub mod model;
pub mod square;
pub mod trace;

pub use geometry::{Frame, V3};
pub use install::{InstallParam, Installation};
pub use layout::{Layout, LayoutError};
pub use model::{Pose, Readings};
pub use trace::{Invalid, InvalidKind, Spot};
