//! The twin's three-axis machine (issue 27): three linear axes in a kinematic chain, each with
//! the six component errors of a mid-size machine, three squarenesses, and a CNC that applies
//! a volumetric compensation to its setpoints as Beckhoff's does (the tool point, not its
//! orientation). It composes the chain exactly (rotation matrices, unit axis lines), so the
//! truth after a compensation is known at any point of the volume with any tool offset.
//!
//! The machine's frame is its axes' reference lines (ISO 230-1): every straightness is
//! taken from its axis's least-squares line, and the squarenesses are the angles between
//! those lines. Each axis is drawn as the single-axis twin draws one (`sim::axis::AxisProfile`, in the
//! head's frame, put on the machine by the standard mounting `AxisMapping::standard`), with
//! neither screw-periodic term nor reversal: those stay with each axis's own compensation
//! (issue 15), a volumetric model takes the smooth geometry. Conventions: `machine::model`.

use super::Rng;
use super::axis::{AxisProfile, AxisSpec, Direction};
use super::plant::PlantSpec;
use crate::comp::mapping::{AxisMapping, MachineAxis};
use crate::evaluate::ReferenceLine;
use crate::evaluate::iso230_1::fit_line;
use crate::machine::squareness::{SquareCertificate, SquarePair};
use crate::machine::{Chain, ComponentTable, MachineError, MachineModel, Squareness, Volumetric};
use crate::optics::square::OpticalSquare;
use crate::units::RAD_PER_ARCSEC;
use nalgebra::{Rotation3, Vector3};
use std::time::Instant;

/// How large the twin machine and its errors are: each axis's peak drawn uniformly from its
/// range, each squareness's magnitude from its range with a random sign.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct MachineSpec {
    /// Travel of X, Y, Z (mm), each from 0.
    pub travel_mm: [f64; 3],
    pub chain: Chain,
    /// Peak positioning error (µm).
    pub positioning_um: (f64, f64),
    /// Peak of each straightness (µm).
    pub straightness_um: (f64, f64),
    /// Peak of each angular error, roll included (arcsec).
    pub angle_arcsec: (f64, f64),
    /// |squareness| (arcsec).
    pub squareness_arcsec: (f64, f64),
}

impl MachineSpec {
    /// A vertical machining centre with a cross table, X 1000 × Y 600 × Z 500 mm.
    pub fn vertical_mc() -> MachineSpec {
        MachineSpec {
            travel_mm: [1000.0, 600.0, 500.0],
            chain: Chain::cross_table(),
            positioning_um: (15.0, 30.0),
            straightness_um: (10.0, 20.0),
            angle_arcsec: (5.0, 10.0),
            squareness_arcsec: (5.0, 20.0),
        }
    }

    /// A gantry, X 2000 × Y 1500 × Z 600 mm.
    pub fn gantry() -> MachineSpec {
        MachineSpec {
            travel_mm: [2000.0, 1500.0, 600.0],
            chain: Chain::gantry(),
            ..MachineSpec::vertical_mc()
        }
    }
}

/// The tool point's volumetric error over a set of points (mm).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct VolumetricFigures {
    pub points: usize,
    pub max_mm: f64,
    pub rms_mm: f64,
}

/// The twin machine, drawn once from its spec and a seed.
#[derive(Clone, Debug)]
pub struct TwinMachine {
    pub spec: MachineSpec,
    /// X, Y, Z: each axis as the single-axis twin draws it from `seeds` and `axis_specs`.
    axes: [AxisProfile; 3],
    axis_specs: [AxisSpec; 3],
    seeds: [u64; 3],
    /// Each axis's two straightnesses' least-squares lines over its travel, in the head's
    /// frame (dx, dz): (intercept mm, slope).
    lines: [[(f64, f64); 2]; 3],
    squareness: Squareness,
}

/// The least-squares line (intercept, slope) of `f` over `[0, len]`, from 1001 samples.
fn line_of(len: f64, f: impl Fn(f64) -> f64) -> (f64, f64) {
    let xs: Vec<f64> = (0..=1000).map(|i| len * i as f64 / 1000.0).collect();
    let ys: Vec<f64> = xs.iter().map(|&x| f(x)).collect();
    fit_line(&xs, &ys, ReferenceLine::LeastSquares)
        .map_or((0.0, 0.0), |l| (l.intercept_mm, l.slope))
}

/// A rotation vector (rad) as the exact rotation Rz(c)·Ry(b)·Rx(a).
fn rotation(e: [f64; 3]) -> Rotation3<f64> {
    Rotation3::from_euler_angles(e[0], e[1], e[2])
}

impl TwinMachine {
    pub fn new(spec: &MachineSpec, seed: u64) -> TwinMachine {
        let mut rng = Rng::new(seed);
        let axis_specs: [AxisSpec; 3] = std::array::from_fn(|i| {
            let angle = rng.uniform(spec.angle_arcsec.0, spec.angle_arcsec.1);
            AxisSpec {
                length_mm: spec.travel_mm[i],
                positioning_um: rng.uniform(spec.positioning_um.0, spec.positioning_um.1),
                periodic_um: 0.0,
                backlash_um: 0.0,
                straightness_um: rng.uniform(spec.straightness_um.0, spec.straightness_um.1),
                pitch_yaw_arcsec: angle,
                roll_arcsec: rng.uniform(spec.angle_arcsec.0, spec.angle_arcsec.1),
                thermal_um_per_m_per_h: 0.0,
                ..AxisSpec::default()
            }
        });
        let seeds: [u64; 3] = std::array::from_fn(|_| rng.next_u64() >> 11);
        // As `sim::plant::Plant::new` draws its axis from its seed: the single-axis twin of
        // `plant_spec` carries this very axis.
        let axes: [AxisProfile; 3] = std::array::from_fn(|i| {
            AxisProfile::random(&axis_specs[i], &mut Rng::new(seeds[i]).fork(12))
        });
        let lines = std::array::from_fn(|i| {
            let len = spec.travel_mm[i];
            let e = |q: f64| axes[i].errors(q, Direction::Up, 0.0).to_array();
            [line_of(len, |q| e(q)[0]), line_of(len, |q| e(q)[2])]
        });
        let mut square = || {
            let m = rng.uniform(spec.squareness_arcsec.0, spec.squareness_arcsec.1);
            let sign = if rng.unit() < 0.5 { -1.0 } else { 1.0 };
            sign * m * RAD_PER_ARCSEC
        };
        let squareness = Squareness {
            c0y: square(),
            b0z: square(),
            a0z: square(),
        };
        TwinMachine {
            spec: *spec,
            axes,
            axis_specs,
            seeds,
            lines,
            squareness,
        }
    }

    /// The single-axis twin's plant for `axis` (the rest from `base`): its axis is this
    /// machine's, as the head measures it on its own.
    pub fn plant_spec(&self, axis: MachineAxis, base: PlantSpec) -> PlantSpec {
        PlantSpec {
            seed: self.seeds[axis.index()],
            axis: self.axis_specs[axis.index()],
            ..base
        }
    }

    /// `axis` as the single-axis twin draws it, in the head's frame.
    pub fn axis_profile(&self, axis: MachineAxis) -> &AxisProfile {
        &self.axes[axis.index()]
    }

    /// The true squarenesses (rad).
    pub fn squareness(&self) -> Squareness {
        self.squareness
    }

    /// The true six component errors of `axis` at `q` (mm): translations along X, Y, Z (mm),
    /// rotations about X, Y, Z (rad). The straightnesses are those from the axis's reference
    /// line (ISO 230-1: its least-squares line), so the squarenesses are the angles between
    /// the reference lines, as an optical square measures them; the single-axis twin's
    /// straightness is this plus a line (where its beam happens to point).
    pub fn component_errors(&self, axis: MachineAxis, q: f64) -> [f64; 6] {
        let i = axis.index();
        let mut e = self.axes[i].errors(q, Direction::Up, 0.0).to_array();
        for (k, (a, b)) in [0, 2].into_iter().zip(self.lines[i]) {
            e[k] -= a + b * q;
        }
        let m = AxisMapping::standard(axis);
        let t = m.to_machine([e[0], e[1], e[2]]);
        let r = m.to_machine([e[3], e[4], e[5]]);
        [t[0], t[1], t[2], r[0], r[1], r[2]]
    }

    /// `axis`' unit line, exactly.
    pub fn direction(&self, axis: MachineAxis) -> Vector3<f64> {
        let s = self.squareness;
        match axis {
            MachineAxis::X => Vector3::x(),
            MachineAxis::Y => rotation([0.0, 0.0, s.c0y]) * Vector3::y(),
            MachineAxis::Z => {
                rotation([s.a0z, 0.0, 0.0]) * rotation([0.0, s.b0z, 0.0]) * Vector3::z()
            }
        }
    }

    /// Where the tool's point is in the workpiece frame (mm) when the axes stand at `cmd`
    /// (mm) with tool offset `tool` (mm): the chain composed exactly.
    pub fn tool_point(&self, cmd: [f64; 3], tool: [f64; 3]) -> [f64; 3] {
        let mut p = Vector3::from(tool);
        for &axis in self.spec.chain.order().iter().rev() {
            let q = cmd[axis.index()];
            let e = self.component_errors(axis, q);
            p = rotation([e[3], e[4], e[5]]) * p
                + self.direction(axis) * q
                + Vector3::new(e[0], e[1], e[2]);
        }
        [p.x, p.y, p.z]
    }

    /// The tool point's error (mm) at `cmd` with `tool`, uncompensated.
    pub fn error(&self, cmd: [f64; 3], tool: [f64; 3]) -> [f64; 3] {
        let p = self.tool_point(cmd, tool);
        std::array::from_fn(|k| p[k] - cmd[k] - tool[k])
    }

    /// The tool point's error (mm) at `cmd` with `tool` when the CNC compensates by `model`
    /// (a model or a grid): each axis's setpoint shifted by the error it expects at the
    /// programmed point, taken back.
    pub fn error_compensated(
        &self,
        cmd: [f64; 3],
        tool: [f64; 3],
        model: &dyn Volumetric,
    ) -> [f64; 3] {
        let e = model.error_at(cmd, tool);
        let set = std::array::from_fn(|k| cmd[k] - e[k]);
        let p = self.tool_point(set, tool);
        std::array::from_fn(|k| p[k] - cmd[k] - tool[k])
    }

    /// The model of the true errors, each axis's table sampled every `step_mm` over its
    /// travel: what a perfect measurement would give.
    pub fn truth_model(&self, step_mm: f64) -> Result<MachineModel, MachineError> {
        let tables = MachineAxis::ALL
            .into_iter()
            .map(|a| {
                ComponentTable::sample(a, 0.0, self.spec.travel_mm[a.index()], step_mm, |q| {
                    self.component_errors(a, q)
                })
            })
            .collect::<Result<Vec<_>, _>>()?;
        MachineModel::new(self.spec.chain, tables, self.squareness)
    }

    /// The largest |measured − truth| of each of `table`'s six errors at its positions:
    /// positioning and angles relative to the truth at 0 mm (where the head took its zero),
    /// each straightness after the least-squares line through the difference (the truth over
    /// these positions keeps a small line of its own).
    pub fn worst_off(&self, table: &ComponentTable) -> [f64; 6] {
        let axis = table.axis();
        let p = table.positions_mm();
        let at0 = self.component_errors(axis, 0.0);
        std::array::from_fn(|k| {
            let straight = k < 3 && k != axis.index();
            let d: Vec<f64> = p
                .iter()
                .zip(table.values())
                .map(|(&q, m)| {
                    let t = self.component_errors(axis, q)[k];
                    m[k] - if straight { t } else { t - at0[k] }
                })
                .collect();
            let left = match fit_line(p, &d, ReferenceLine::LeastSquares) {
                Some(line) if straight => line.residuals,
                _ => d,
            };
            left.iter().fold(0.0f64, |a, v| a.max(v.abs()))
        })
    }

    /// The tool point's error over `points` with `tool` (mm), uncompensated (`None`) or with
    /// the CNC compensating by `model`: its largest and RMS magnitude.
    pub fn volumetric(
        &self,
        points: &[[f64; 3]],
        tool: [f64; 3],
        model: Option<&dyn Volumetric>,
    ) -> VolumetricFigures {
        let e: Vec<f64> = points
            .iter()
            .map(|&p| {
                let v = match model {
                    Some(m) => self.error_compensated(p, tool, m),
                    None => self.error(p, tool),
                };
                v.iter().map(|x| x * x).sum::<f64>().sqrt()
            })
            .collect();
        let n = e.len().max(1) as f64;
        VolumetricFigures {
            points: e.len(),
            max_mm: e.iter().fold(0.0f64, |a, &b| a.max(b)),
            rms_mm: (e.iter().map(|v| v * v).sum::<f64>() / n).sqrt(),
        }
    }

    /// `n` points drawn uniformly in the volume (mm).
    pub fn random_points(&self, n: usize, rng: &mut Rng) -> Vec<[f64; 3]> {
        (0..n)
            .map(|_| std::array::from_fn(|k| rng.uniform(0.0, self.spec.travel_mm[k])))
            .collect()
    }
}

/// A twin's optical square: the pentaprism as it is (its true deviation from 90°, its axis
/// tilted as a technician sets it down) and what its certificate says of it.
#[derive(Clone, Debug, PartialEq)]
pub struct TwinSquare {
    pub prism: OpticalSquare,
    pub certificate: SquareCertificate,
}

/// A square's true deviation from 90° is drawn within ± this (arcsec); its certificate states
/// it within ± this tolerance (arcsec: rectangular, u = a/√3), the truth anywhere inside it;
/// its axis is set down within ± this of the pair's (degrees, about the incoming beam).
const SQUARE_DEVIATION_ARCSEC: f64 = 3.0;
const SQUARE_TOLERANCE_ARCSEC: f64 = 0.5;
const SQUARE_TILT_DEG: f64 = 0.05;

impl TwinSquare {
    /// A square for `pair`, drawn from `seed`.
    pub fn draw(pair: SquarePair, seed: u64) -> TwinSquare {
        let mut rng = Rng::new(seed);
        let truth = rng.uniform(-SQUARE_DEVIATION_ARCSEC, SQUARE_DEVIATION_ARCSEC) * RAD_PER_ARCSEC;
        let a = SQUARE_TOLERANCE_ARCSEC * RAD_PER_ARCSEC;
        let stated = truth + rng.uniform(-a, a);
        let u = a / 3f64.sqrt();
        let (first, _) = pair.axes();
        let tilt = rng.uniform(-SQUARE_TILT_DEG, SQUARE_TILT_DEG).to_radians();
        let incoming = Vector3::from(AxisMapping::standard(first).to_machine([0.0, 1.0, 0.0]));
        let axis = Rotation3::from_axis_angle(&nalgebra::Unit::new_normalize(incoming), tilt)
            * pair.square_axis();
        TwinSquare {
            prism: OpticalSquare::new(axis, truth).unwrap_or_else(|| {
                unreachable!("a unit axis and a finite deviation make a square")
            }),
            certificate: SquareCertificate {
                id: format!("twin square {seed}"),
                deviation_rad: stated,
                u_rad: u,
            },
        }
    }
}

/// The head's frame on a set-up of `axis` whose beam runs along `beam` (machine frame): y the
/// beam, x and z the standard mounting's, squared to it.
fn head_frame(axis: MachineAxis, beam: Vector3<f64>) -> [Vector3<f64>; 3] {
    let m = AxisMapping::standard(axis);
    let y = beam.normalize();
    let x0 = Vector3::from(m.to_machine([1.0, 0.0, 0.0]));
    let x = (x0 - y * x0.dot(&y)).normalize();
    [x, y, x.cross(&y)]
}

impl TwinMachine {
    /// The slopes (along the head's x and z) a head on `axis` reads when its beam runs along
    /// `beam` (machine frame): the axis's line against the beam.
    pub fn slopes_for_beam(&self, axis: MachineAxis, beam: Vector3<f64>) -> [f64; 2] {
        let [x, y, z] = head_frame(axis, beam);
        let line = self.direction(axis);
        [line.dot(&x) / line.dot(&y), line.dot(&z) / line.dot(&y)]
    }

    /// The beam (machine frame, unit) of a set-up on `axis` whose head reads the true slopes
    /// `slopes`: the inverse of [`TwinMachine::slopes_for_beam`].
    pub fn beam_of(&self, axis: MachineAxis, slopes: [f64; 2]) -> Vector3<f64> {
        let line = self.direction(axis);
        let mut beam = line;
        // The head's frame depends on the beam: a few fixed-point steps (each error shrinks
        // by the slopes' size, 1e-4).
        for _ in 0..4 {
            let [x, y, z] = head_frame(axis, beam);
            let along = line.dot(&y);
            beam = (line - x * slopes[0] * along - z * slopes[1] * along).normalize();
        }
        beam
    }
}

/// The head on a plant set up through an optical square: its beam's direction in the square's
/// plane is the square's, not the technician's. After the usual alignment (every screw), the
/// mount's angle that turns the beam in that plane (yaw for the head's x, pitch for its z) is
/// set so that the head reads `slope` over `span` along its x (`j` 0) or its z (`j` 1), as
/// `Plant::true_slopes` indexes them. The set slope, as the plant's truth gives it.
pub fn hold_in_plane(
    plant: &super::plant::Plant,
    span: (f64, f64),
    j: usize,
    slope: f64,
    now: Instant,
) -> f64 {
    use crate::align::Mount;
    let turn = |a: f64| {
        if j == 0 {
            Mount {
                yaw: a,
                ..Mount::default()
            }
        } else {
            Mount {
                pitch: a,
                ..Mount::default()
            }
        }
    };
    let probe = 1e-5;
    for _ in 0..3 {
        let before = plant.true_slopes(span, now)[j];
        plant.knock(turn(probe));
        let gain = (plant.true_slopes(span, now)[j] - before) / probe;
        plant.knock(turn(-probe));
        if gain.is_nan() || gain.abs() <= 1e-3 {
            break;
        }
        plant.knock(turn((slope - before) / gain));
    }
    plant.true_slopes(span, now)[j]
}
