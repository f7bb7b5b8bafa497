//! Skew-ray tracing (DESIGN §2): a ray `p + t·d`, plane intersection
//! `t = n·(o − p)/(n·d)` (a miss when `|n·d|` is tiny or `t ≤ 0`), reflection `d' = d − 2(d·n)n`,
//! thin transmitting elements leave `d` unchanged, the ideal corner cube returns along `−d`
//! through `2A − q_in`, polarisation is a label. Pure functions; a miss is an `Err`, never NaN.

use super::geometry::{Frame, V3};
use super::layout::{Action, Aperture, Element, Kind, OpticalPath, Polarisation};

/// Below this `|n·d|` the ray is taken as parallel to the plane.
const PARALLEL_TOL: f64 = 1e-12;
/// A hit must lie at least this far ahead (mm) of the ray's start.
const AHEAD_TOL: f64 = 1e-9;

/// A ray: start point (mm), unit direction, polarisation label.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Ray {
    pub p: V3,
    pub d: V3,
    pub pol: Polarisation,
}

/// A spot on a PSD in the PSD's own frame (mm), gains applied.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Spot {
    pub x: f64,
    pub y: f64,
}

/// Why a path gave no reading.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum InvalidKind {
    /// The ray runs parallel to the element's plane or the plane lies behind it.
    Miss,
    /// The ray meets the plane outside the element's aperture (in-plane point a, b in mm).
    Aperture { a: f64, b: f64 },
    /// The spot is off the PSD's active area (X, Y in mm).
    OffActiveArea { x: f64, y: f64 },
    /// A PBS step saw the wrong polarisation.
    Polarisation { got: Polarisation },
}

/// Where and why a path failed: path index (0..3), step index within it, and the reason.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Invalid {
    pub path: usize,
    pub step: usize,
    pub element: usize,
    pub kind: InvalidKind,
}

impl Invalid {
    /// One-line description with element and path names.
    pub fn describe(&self, elements: &[Element], paths: &[OpticalPath; 3]) -> String {
        let el = elements
            .get(self.element)
            .map(|e| e.name.as_str())
            .unwrap_or("?");
        let path = paths.get(self.path).map(|p| p.name.as_str()).unwrap_or("?");
        let step = self.step + 1;
        match self.kind {
            InvalidKind::Miss => {
                format!("{path} step {step}: the beam misses {el} (parallel to it or behind it)")
            }
            InvalidKind::Aperture { a, b } => {
                let lim = elements.get(self.element).map(|e| e.aperture);
                let r = (a * a + b * b).sqrt();
                match lim {
                    Some(Aperture::Circle { radius }) => format!(
                        "{path} step {step}: the beam passes {el} {r:.3} mm from its centre, outside its {radius} mm aperture"
                    ),
                    _ => format!(
                        "{path} step {step}: the beam passes {el} at ({a:.3}, {b:.3}) mm, outside its aperture"
                    ),
                }
            }
            InvalidKind::OffActiveArea { x, y } => {
                let half = match elements.get(self.element).map(|e| e.aperture) {
                    Some(Aperture::Square { half }) | Some(Aperture::Circle { radius: half }) => {
                        half
                    }
                    None => f64::NAN,
                };
                format!(
                    "{path}: spot off {el} active area at X = {x:.3} mm, Y = {y:.3} mm (half-size {half} mm)"
                )
            }
            InvalidKind::Polarisation { got } => format!(
                "{path} step {step}: {el} needs the other polarisation, the beam is {}",
                got.name()
            ),
        }
    }
}

/// Intersection of the ray with the plane through `o` with normal `n`: the hit point, or `None`
/// for a miss (parallel, or not ahead).
#[inline]
pub fn intersect_plane(p: V3, d: V3, o: V3, n: V3) -> Option<V3> {
    let nd = n.dot(&d);
    if nd.abs() < PARALLEL_TOL {
        return None;
    }
    let t = n.dot(&(o - p)) / nd;
    if t <= AHEAD_TOL {
        return None;
    }
    Some(p + d * t)
}

/// Mirror reflection of direction `d` on a plane with unit normal `n`.
#[inline]
pub fn reflect(d: V3, n: V3) -> V3 {
    d - n * (2.0 * d.dot(&n))
}

/// The ideal corner cube with apex `apex`, unit axis `axis` (out of the opening), opening at
/// `depth`: the entry point on the opening plane, and the returned ray (start `2A − q_in`,
/// direction `−d`). `None` when the ray misses the opening plane.
#[inline]
pub fn corner_cube(p: V3, d: V3, apex: V3, axis: V3, depth: f64) -> Option<(V3, V3, V3)> {
    let q_in = intersect_plane(p, d, apex + axis * depth, axis)?;
    Some((q_in, apex * 2.0 - q_in, -d))
}

/// Trace one path. `frame_of(i)` gives element `i`'s frame at the current pose. With
/// `apertures` false, apertures and active areas are not checked (geometry only).
#[inline]
pub fn trace_path(
    elements: &[Element],
    path: &OpticalPath,
    path_index: usize,
    apertures: bool,
    frame_of: impl Fn(usize) -> Frame,
) -> Result<Spot, Invalid> {
    let fail = |step: usize, element: usize, kind: InvalidKind| Invalid {
        path: path_index,
        step,
        element,
        kind,
    };
    let mut ray = Ray {
        p: V3::zeros(),
        d: V3::zeros(),
        pol: Polarisation::P,
    };
    for (si, step) in path.steps.iter().enumerate() {
        let el = &elements[step.element];
        let f = frame_of(step.element);
        if step.action == Action::Source {
            ray = Ray {
                p: f.o(),
                d: f.n(),
                pol: Polarisation::P,
            };
            continue;
        }
        if step.action == Action::Retro {
            let Kind::CornerCube { depth } = el.kind else {
                return Err(fail(si, step.element, InvalidKind::Miss));
            };
            let (apex, axis) = (f.o(), f.n());
            let (q_in, p_out, d_out) = corner_cube(ray.p, ray.d, apex, axis, depth)
                .ok_or_else(|| fail(si, step.element, InvalidKind::Miss))?;
            let w = q_in - (apex + axis * depth);
            let (a, b) = (w.dot(&f.u()), w.dot(&f.v()));
            if apertures && !el.aperture.contains(a, b) {
                return Err(fail(si, step.element, InvalidKind::Aperture { a, b }));
            }
            ray.p = p_out;
            ray.d = d_out;
            continue;
        }
        let (o, n) = (f.o(), f.n());
        let q = intersect_plane(ray.p, ray.d, o, n)
            .ok_or_else(|| fail(si, step.element, InvalidKind::Miss))?;
        let w = q - o;
        let (a, b) = (w.dot(&f.u()), w.dot(&f.v()));
        if step.action == Action::Detect {
            if apertures && !el.aperture.contains(a, b) {
                return Err(fail(
                    si,
                    step.element,
                    InvalidKind::OffActiveArea { x: a, y: b },
                ));
            }
            return Ok(Spot {
                x: a * el.gain[0],
                y: b * el.gain[1],
            });
        }
        if apertures && !el.aperture.contains(a, b) {
            return Err(fail(si, step.element, InvalidKind::Aperture { a, b }));
        }
        ray.p = q;
        match step.action {
            Action::Transmit => {}
            Action::Reflect => ray.d = reflect(ray.d, n),
            Action::PbsTransmit | Action::PbsReflect => {
                let needed = if step.action == Action::PbsTransmit {
                    Polarisation::P
                } else {
                    Polarisation::S
                };
                if ray.pol != needed {
                    return Err(fail(
                        si,
                        step.element,
                        InvalidKind::Polarisation { got: ray.pol },
                    ));
                }
                if step.action == Action::PbsReflect {
                    ray.d = reflect(ray.d, n);
                }
            }
            Action::Qwp => ray.pol = ray.pol.after_qwp(),
            Action::Source | Action::Retro | Action::Detect => {}
        }
    }
    // Validation guarantees the last step is Detect; a path without one reads nothing.
    Err(fail(
        path.steps.len().saturating_sub(1),
        path.psd,
        InvalidKind::Miss,
    ))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::optics::geometry::rot_zyx;
    use crate::sim::rng::Rng;

    /// Explicit hollow corner cube: three mutually perpendicular mirrors meeting at the apex,
    /// face normals `m[i]` pointing into the cube's interior (towards the opening). Each face is
    /// the part of its plane where the other two face coordinates are positive.
    fn three_mirror_trace(p0: V3, d0: V3, apex: V3, m: [V3; 3]) -> Option<(V3, V3, usize)> {
        let (mut p, mut d) = (p0, d0);
        let mut hits = 0;
        let mut last: Option<usize> = None;
        for _ in 0..3 {
            let mut best: Option<(f64, usize, V3)> = None;
            for (i, ni) in m.iter().enumerate() {
                if Some(i) == last {
                    continue;
                }
                let nd = ni.dot(&d);
                if nd.abs() < 1e-15 {
                    continue;
                }
                let t = ni.dot(&(apex - p)) / nd;
                if t <= 1e-12 {
                    continue;
                }
                let q = p + d * t;
                let w = q - apex;
                let inside = (0..3).filter(|&j| j != i).all(|j| w.dot(&m[j]) >= -1e-12);
                if inside && best.is_none_or(|b| t < b.0) {
                    best = Some((t, i, q));
                }
            }
            let (_, i, q) = best?;
            p = q;
            d = reflect(d, m[i]);
            last = Some(i);
            hits += 1;
        }
        Some((p, d, hits))
    }

    #[test]
    fn corner_cube_rule_matches_three_mirror_trace() {
        let mut rng = Rng::new(7);
        for _ in 0..500 {
            // A random cube orientation; its axis is the diagonal of the three face normals.
            let r = rot_zyx(
                rng.uniform(-3.0, 3.0),
                rng.uniform(-1.5, 1.5),
                rng.uniform(-3.0, 3.0),
            );
            let m: [V3; 3] = [r.column(0).into(), r.column(1).into(), r.column(2).into()];
            let axis = (m[0] + m[1] + m[2]).normalize();
            let apex = V3::new(
                rng.uniform(-50.0, 50.0),
                rng.uniform(-50.0, 50.0),
                rng.uniform(-50.0, 50.0),
            );
            let depth = 15.0;
            // An incoming ray a few degrees off the axis, entering within 5 mm of the centre.
            let tilt = rot_zyx(rng.uniform(-0.05, 0.05), rng.uniform(-0.05, 0.05), 0.0);
            let d = -(r * tilt * r.transpose() * axis).normalize();
            let e1 = axis.cross(&V3::new(0.3, 0.7, 0.1)).normalize();
            let e2 = axis.cross(&e1);
            let entry =
                apex + axis * depth + e1 * rng.uniform(-5.0, 5.0) + e2 * rng.uniform(-5.0, 5.0);
            let p = entry - d * 100.0;

            let (q_in, p_rule, d_rule) = corner_cube(p, d, apex, axis, depth).unwrap();
            assert!((q_in - entry).norm() < 1e-9);
            let (p_exp, d_exp, hits) = three_mirror_trace(p, d, apex, m).unwrap();
            assert_eq!(hits, 3);
            assert!((d_exp - d_rule).norm() < 1e-12, "direction");
            // The explicit exit point lies on the rule's line.
            let off = (p_exp - p_rule) - d_rule * (p_exp - p_rule).dot(&d_rule);
            assert!(off.norm() < 1e-9, "offset {}", off.norm());
        }
    }

    #[test]
    fn plane_miss_cases() {
        let o = V3::new(0.0, 10.0, 0.0);
        let n = V3::new(0.0, 1.0, 0.0);
        assert!(intersect_plane(V3::zeros(), V3::new(1.0, 0.0, 0.0), o, n).is_none());
        assert!(intersect_plane(V3::zeros(), V3::new(0.0, -1.0, 0.0), o, n).is_none());
        let q = intersect_plane(V3::zeros(), V3::new(0.0, 1.0, 0.0), o, n).unwrap();
        assert!((q - o).norm() < 1e-12);
    }
}
