//! Commissioning a whole machine (issue 27): the machine record as its builder writes it
//! (`record`, its one reader), the commissioning plan that walks the technician through the
//! set-ups in order (`plan`), the 21-error model fitted from the measured set-ups (`fit`), a
//! machine as the store keeps it, each set-up's run attached and checked (`stored`), and the
//! machine acceptance report (`report`).
//!
//! Above `machine` (the model, the squareness, the controls' files) and the store; the
//! service, the command line and the console show it, and `sim::machine_lab` walks the same
//! plan on the twin.

pub mod fit;
pub mod plan;
pub mod record;
pub mod report;
pub mod stored;

pub use fit::{MachineFit, MeasuredSetup};
pub use plan::{Beam, SETUPS, SetupState};
pub use record::{MachineRecord, RecordError};
pub use stored::{CommissionError, MachineState};

#[cfg(test)]
mod tests;
