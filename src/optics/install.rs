//! Installation errors of a head: per element an offset (mm, along the element's own u, v, n
//! axes), a tilt (rad, about those axes, about its origin) and, for PSDs, a relative gain error
//! of the (X, Y) readings. The digital twin draws them at random; the model-based calibration
//! estimates the ones that change readings.

use super::geometry::{V3, rot_zyx};
use super::layout::{Element, Kind, Layout};
use serde::{Deserialize, Serialize};
use std::collections::BTreeMap;

/// Installation error of one element.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct ElementInstall {
    /// Offset of the origin along the element's u, v, n (mm).
    pub offset: [f64; 3],
    /// Small rotation about the element's own u, v, n axes (rad), x-first order.
    pub tilt: [f64; 3],
    /// Relative gain error of the PSD's X and Y readings (0 = nominal).
    pub gain_error: [f64; 2],
}

/// One scalar installation parameter of an element.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum InstallParam {
    /// Offset along the element's u, v or n (0, 1, 2).
    Offset(usize),
    /// Tilt about the element's u, v or n (0, 1, 2).
    Tilt(usize),
    /// PSD gain error of X or Y (0, 1).
    Gain(usize),
}

impl InstallParam {
    /// Short label such as `offset_y` or `tilt_u`.
    pub fn label(self) -> &'static str {
        match self {
            InstallParam::Offset(0) => "offset_u",
            InstallParam::Offset(1) => "offset_v",
            InstallParam::Offset(_) => "offset_n",
            InstallParam::Tilt(0) => "tilt_u",
            InstallParam::Tilt(1) => "tilt_v",
            InstallParam::Tilt(_) => "tilt_n",
            InstallParam::Gain(0) => "gain_x",
            InstallParam::Gain(_) => "gain_y",
        }
    }
}

/// Installation errors of every element of a layout, in the layout's element order.
#[derive(Clone, Debug, PartialEq)]
pub struct Installation {
    pub elements: Vec<ElementInstall>,
}

impl Installation {
    /// No installation error.
    pub fn none(layout: &Layout) -> Self {
        Installation {
            elements: vec![ElementInstall::default(); layout.elements.len()],
        }
    }

    /// The layout with these errors applied to the nominal frames and gains.
    pub fn apply(&self, nominal: &Layout) -> Layout {
        let elements: Vec<Element> = nominal
            .elements
            .iter()
            .zip(&self.elements)
            .map(|(el, inst)| {
                let r = rot_zyx(inst.tilt[0], inst.tilt[1], inst.tilt[2]);
                let mut out = el.clone();
                out.frame = el.frame.perturbed(V3::from(inst.offset), &r);
                if el.kind == Kind::Psd {
                    out.gain = [
                        el.gain[0] * (1.0 + inst.gain_error[0]),
                        el.gain[1] * (1.0 + inst.gain_error[1]),
                    ];
                }
                out
            })
            .collect();
        nominal.with_elements(elements)
    }

    /// Value of one parameter.
    pub fn get(&self, element: usize, p: InstallParam) -> f64 {
        let e = &self.elements[element];
        match p {
            InstallParam::Offset(i) => e.offset[i],
            InstallParam::Tilt(i) => e.tilt[i],
            InstallParam::Gain(i) => e.gain_error[i],
        }
    }

    /// Set one parameter.
    pub fn set(&mut self, element: usize, p: InstallParam, value: f64) {
        let e = &mut self.elements[element];
        match p {
            InstallParam::Offset(i) => e.offset[i] = value,
            InstallParam::Tilt(i) => e.tilt[i] = value,
            InstallParam::Gain(i) => e.gain_error[i] = value,
        }
    }

    /// As a table keyed by element name (for calibration files).
    pub fn to_named(&self, layout: &Layout) -> BTreeMap<String, ElementInstall> {
        layout
            .elements
            .iter()
            .zip(&self.elements)
            .filter(|(_, i)| **i != ElementInstall::default())
            .map(|(el, i)| (el.name.clone(), *i))
            .collect()
    }

    /// From a table keyed by element name; names the first unknown element.
    pub fn from_named(
        layout: &Layout,
        named: &BTreeMap<String, ElementInstall>,
    ) -> Result<Self, String> {
        let mut out = Installation::none(layout);
        for (name, inst) in named {
            let i = layout
                .element_index(name)
                .ok_or_else(|| format!("element {name} is not in the layout"))?;
            out.elements[i] = *inst;
        }
        Ok(out)
    }
}

/// The installation parameters that change readings, per element kind. An ideal plane
/// element is blind to offsets within its plane and to turns about its normal; a thin
/// quarter-wave plate to everything; an ideal corner cube to any turn about its apex; a laser to
/// moving along or turning about its own beam. (A corner cube moved along its axis still shows:
/// the module turns about C, so the apex's lever changes.)
pub fn observable_params(layout: &Layout) -> Vec<(usize, InstallParam)> {
    use InstallParam::{Gain, Offset, Tilt};
    let mut out = Vec::new();
    for (i, el) in layout.elements.iter().enumerate() {
        let params: &[InstallParam] = match el.kind {
            Kind::Laser => &[Offset(0), Offset(1), Tilt(0), Tilt(1)],
            Kind::Bs | Kind::Pbs | Kind::Mirror => &[Offset(2), Tilt(0), Tilt(1)],
            Kind::Qwp => &[],
            Kind::CornerCube { .. } => &[Offset(0), Offset(1), Offset(2)],
            Kind::Psd => &[
                Offset(0),
                Offset(1),
                Offset(2),
                Tilt(0),
                Tilt(1),
                Tilt(2),
                Gain(0),
                Gain(1),
            ],
        };
        out.extend(params.iter().map(|p| (i, *p)));
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::optics::model::Pose;
    use crate::units::Errors6;

    #[test]
    fn unobservable_params_change_nothing() {
        let l = Layout::reference();
        let obs = observable_params(&l);
        let pose = Pose::new(
            Errors6::from_user([30.0, -20.0, 10.0, 5.0, -8.0, 12.0]),
            0.0,
            0.0,
        );
        let r0 = l.forward(&pose).vector().unwrap();
        for (i, el) in l.elements.iter().enumerate() {
            let all = (0..3)
                .map(InstallParam::Offset)
                .chain((0..3).map(InstallParam::Tilt))
                .chain((0..2).map(InstallParam::Gain));
            for p in all {
                if obs.contains(&(i, p)) {
                    continue;
                }
                let mut inst = Installation::none(&l);
                let step = match p {
                    InstallParam::Offset(_) => 0.3,
                    _ => 2e-3,
                };
                inst.set(i, p, step);
                let r = inst.apply(&l).forward(&pose).vector().unwrap();
                assert!(
                    (r - r0).amax() < 1e-10,
                    "{} {} changes readings by {}",
                    el.name,
                    p.label(),
                    (r - r0).amax()
                );
            }
        }
    }

    #[test]
    fn observable_params_change_readings() {
        // On a head with installation errors (so no beam meets a PSD exactly square on) and at
        // large angles (so lever-arm effects show), every fitted parameter moves some reading.
        let nominal = Layout::reference();
        let mut rng = crate::sim::Rng::new(2);
        let head = crate::sim::TwinHead::random(
            &nominal,
            &crate::sim::InstallSpec::default(),
            0.0,
            &mut rng,
        )
        .unwrap();
        let pose = Pose::new(
            Errors6::from_user([30.0, -20.0, 10.0, 100.0, -80.0, 120.0]),
            0.0,
            0.0,
        );
        let l = head.truth.clone();
        let r0 = l.forward(&pose).vector().unwrap();
        for (i, p) in observable_params(&l) {
            let mut inst = head.install.clone();
            inst.set(i, p, head.install.get(i, p) + 1e-3);
            let r = inst.apply(&nominal).forward(&pose).vector().unwrap();
            assert!(
                (r - r0).amax() > 1e-8,
                "{} {} has no effect",
                l.elements[i].name,
                p.label()
            );
        }
    }
}
