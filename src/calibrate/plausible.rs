//! Is a calibration plausible for the head it is about to be used on?
//!
//! A fit is self-consistent on its own pose set by construction: a pose set made with another
//! head (or another layout, or with the hexapod's frame mislabelled) fits just as well, and only
//! shows when the head in use reads through it. So the service judges a calibration on what it
//! can see before accepting it:
//!
//! - **here**: the six errors the calibration reads from the head's current spots. A machine
//!   axis' errors relative to an aligned head are tens of µm and arcseconds; hundreds mean the
//!   calibration describes another head ([`Limits::here_um`], [`Limits::here_arcsec`]);
//! - **residuals**: a fit whose residual RMS on any reading channel is many times a PSD's noise
//!   does not describe its own poses ([`Limits::residual_um`]);
//! - **installation**: a model fit that moves an element by millimetres or tilts it by degrees
//!   describes no head that was assembled to a drawing ([`Limits::install_offset_mm`],
//!   [`Limits::install_tilt_deg`]);
//! - **the fit itself**: rank short of 7, a model fit that did not converge.
//!
//! Each concern is a sentence with the figure and its limit. Accepting a calibration with a
//! concern needs an explicit override (the control request's `force`, the console's `A`).

use super::Calibration;
use crate::optics::Layout;
use crate::units::{DOF_NAMES, DOF_UNITS, Errors6, READING_NAMES};

/// The limits a plausible calibration stays within.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Limits {
    /// The linear errors read at the current spots (µm).
    pub here_um: f64,
    /// The angular errors read at the current spots (arcsec).
    pub here_arcsec: f64,
    /// The residual RMS per reading channel (µm).
    pub residual_um: f64,
    /// An element's fitted installation offset (mm).
    pub install_offset_mm: f64,
    /// An element's fitted installation tilt (degrees).
    pub install_tilt_deg: f64,
}

impl Default for Limits {
    fn default() -> Self {
        Limits {
            here_um: 100.0,
            here_arcsec: 100.0,
            residual_um: 5.0,
            install_offset_mm: 3.0,
            install_tilt_deg: 1.0,
        }
    }
}

/// |x| ≤ limit; a NaN is never within.
fn within(x: f64, limit: f64) -> bool {
    x.abs() <= limit
}

/// The concerns about `c` as sentences (empty: plausible). `here` is what `c` reads from the
/// head's current spots, when the service has them.
pub fn concerns(
    c: &Calibration,
    nominal: &Layout,
    here: Option<&Errors6>,
    limits: &Limits,
) -> Vec<String> {
    let mut out = Vec::new();
    if let Some(here) = here {
        let v = here.to_user();
        let over: Vec<String> = (0..6)
            .filter(|&k| {
                let limit = if k < 3 {
                    limits.here_um
                } else {
                    limits.here_arcsec
                };
                !within(v[k], limit)
            })
            .map(|k| format!("{} {:+.1} {}", DOF_NAMES[k], v[k], DOF_UNITS[k]))
            .collect();
        if !over.is_empty() {
            out.push(format!(
                "at the carriage's current position it reads {} (plausible: within ±{:.0} µm and ±{:.0} arcsec): the pose set was probably made with another head",
                over.join(", "),
                limits.here_um,
                limits.here_arcsec
            ));
        }
    }
    let (resid, which) = match &c.model {
        Some(m) => (m.residual_rms, "model"),
        None => (c.linear.residual_rms, "linear"),
    };
    let over: Vec<String> = (0..6)
        .filter(|&k| !within(resid[k] * 1000.0, limits.residual_um))
        .map(|k| format!("{} {:.2} µm", READING_NAMES[k], resid[k] * 1000.0))
        .collect();
    if !over.is_empty() {
        out.push(format!(
            "the {which} fit's residual RMS is {} (plausible: up to {:.1} µm, a few times a PSD's noise): the fit does not describe its poses",
            over.join(", "),
            limits.residual_um
        ));
    }
    if c.linear.rank < 7 {
        out.push(format!(
            "the linear fit has rank {} of 7: the poses do not move every degree of freedom",
            c.linear.rank
        ));
    }
    if let Some(m) = &c.model {
        if !m.converged {
            out.push(format!(
                "the model fit did not converge in {} iterations",
                m.iterations
            ));
        }
        let tilt_limit = limits.install_tilt_deg.to_radians();
        for (el, i) in nominal.elements.iter().zip(&m.install.elements) {
            let offset = i.offset.iter().fold(0.0f64, |a, x| a.max(x.abs()));
            let tilt = i.tilt.iter().fold(0.0f64, |a, x| a.max(x.abs()));
            if !within(offset, limits.install_offset_mm) || !within(tilt, tilt_limit) {
                out.push(format!(
                    "the model places {} {offset:.2} mm and {:.2}° from its drawing (plausible: within {:.1} mm and {:.1}°)",
                    el.name,
                    tilt.to_degrees(),
                    limits.install_offset_mm,
                    limits.install_tilt_deg
                ));
            }
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::calibrate::{CalibrateOptions, calibrate};
    use crate::sim::{Hexapod, InstallSpec, PoseWindow, Rng, TwinHead};
    use crate::util::progress::Progress;

    #[test]
    fn a_fit_of_its_own_head_is_plausible_and_each_limit_speaks() {
        let layout = Layout::reference();
        let rng = Rng::new(3);
        let head =
            TwinHead::random(&layout, &InstallSpec::default(), 1e-3, &mut rng.fork(1)).unwrap();
        let poses = PoseWindow::default().draw(60, &mut rng.fork(2));
        let (samples, _) =
            Hexapod::default().acquire(&head, &poses, &mut rng.fork(3), &mut Progress::hidden());
        let c = calibrate(
            &samples,
            &layout,
            &CalibrateOptions::default(),
            &mut |_, _| {},
        )
        .unwrap();
        let limits = Limits::default();
        let small = Errors6::from_user([3.0, -2.0, 1.0, 4.0, -5.0, 2.0]);
        assert_eq!(
            concerns(&c, &layout, Some(&small), &limits),
            Vec::<String>::new()
        );

        // Read far off here: named with the figure, in user units.
        let far = Errors6::from_user([3.0, -250.0, 1.0, 4.0, 480.0, 2.0]);
        let got = concerns(&c, &layout, Some(&far), &limits);
        assert_eq!(got.len(), 1, "{got:?}");
        assert!(
            got[0].starts_with(
                "at the carriage's current position it reads dy -250.0 µm, ey +480.0 arcsec"
            ),
            "{}",
            got[0]
        );
        // A NaN is never plausible.
        let nan = Errors6::from_user([f64::NAN, 0.0, 0.0, 0.0, 0.0, 0.0]);
        assert_eq!(concerns(&c, &layout, Some(&nan), &limits).len(), 1);

        // Residuals and a far-fetched installation.
        let mut bad = c.clone();
        let m = bad.model.as_mut().unwrap();
        m.residual_rms[4] = 12e-3;
        m.install.elements[0].offset[1] = 4.5;
        m.converged = false;
        let got = concerns(&bad, &layout, None, &limits);
        assert_eq!(got.len(), 3, "{got:?}");
        assert!(got[0].contains("X3 12.00 µm"), "{}", got[0]);
        assert!(got[1].contains("did not converge"), "{}", got[1]);
        assert!(
            got[2].contains(&format!("{} 4.50 mm", layout.elements[0].name)),
            "{}",
            got[2]
        );
    }
}
