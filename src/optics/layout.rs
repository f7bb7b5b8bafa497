//! The optical layout as data: elements with their module, frame and aperture, and the three
//! paths as ordered (element, action) steps. Loaded from TOML in two stages: `RawLayout`
//! (what the file says) and `Layout` (validated: frames orthonormal and right-handed, every
//! step's action fits its element, polarisation consistent along each path, every PSD read by
//! exactly one path). Errors name the element or the step and say what to change.

use super::geometry::{Frame, V3};
use crate::util::numbers;
use serde::{Deserialize, Serialize};
use std::path::Path as FsPath;
use thiserror::Error;

/// Tolerance for unit length and orthogonality of frame axes.
const FRAME_TOL: f64 = 1e-9;

/// Why a layout was refused.
#[derive(Debug, Error)]
pub enum LayoutError {
    /// The file could not be read.
    #[error("layout {path}: cannot read it: {source}")]
    Io {
        path: String,
        source: std::io::Error,
    },
    /// The file is not valid TOML or does not fit the schema.
    #[error("layout {path}: {message}")]
    Syntax { path: String, message: String },
    /// The content is wrong; `at` names the element or path step ("element BS1",
    /// "path P1 step 5 (BS2 reflect)"), empty for the layout as a whole.
    #[error("layout {path}: {at}{problem}")]
    Invalid {
        path: String,
        at: String,
        problem: String,
    },
}

impl LayoutError {
    fn element(path: &str, element: &str, problem: impl Into<String>) -> Self {
        LayoutError::Invalid {
            path: path.to_string(),
            at: format!("element {element}: "),
            problem: problem.into(),
        }
    }
    fn whole(path: &str, problem: impl Into<String>) -> Self {
        LayoutError::Invalid {
            path: path.to_string(),
            at: String::new(),
            problem: problem.into(),
        }
    }
}

/// What the TOML file says (first stage).
#[derive(Clone, Debug, Deserialize, Serialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct RawLayout {
    pub name: String,
    /// Moving module reference point C (mm).
    pub reference_point_mm: [f64; 3],
    /// Unit vector of nominal travel.
    pub travel_axis: [f64; 3],
    /// Unit vector along which the follower moves PSD2.
    pub follower_axis: [f64; 3],
    /// Path names in reading order: the first gives (X1, Y1), and so on.
    pub reading_paths: Vec<String>,
    #[serde(rename = "element")]
    pub elements: Vec<RawElement>,
    #[serde(rename = "path")]
    pub paths: Vec<RawPath>,
}

/// One element as written.
#[derive(Clone, Debug, Deserialize, Serialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct RawElement {
    pub name: String,
    /// laser, bs, pbs, mirror, qwp, cc, psd
    pub kind: String,
    /// fixed1, fixed2, moving, follower
    pub module: String,
    pub origin_mm: [f64; 3],
    pub u: [f64; 3],
    pub v: [f64; 3],
    pub n: [f64; 3],
    /// Circle: radius; square: half-size (mm).
    pub aperture_mm: f64,
    /// circle or square
    pub aperture_shape: String,
    /// Corner cube only: distance from apex to the opening plane (mm).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub cc_depth_mm: Option<f64>,
    /// PSD only: gain of the (X, Y) readings, 1 when absent.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub gain: Option<[f64; 2]>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub note: Option<String>,
}

/// One path as written: `steps = [["LASER", "source"], ...]`.
#[derive(Clone, Debug, Deserialize, Serialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct RawPath {
    pub name: String,
    pub steps: Vec<[String; 2]>,
}

/// Element kind.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Kind {
    Laser,
    /// Non-polarising beam splitter (or partially reflecting flat).
    Bs,
    /// Polarising beam splitter.
    Pbs,
    Mirror,
    /// Quarter-wave plate.
    Qwp,
    /// Ideal hollow corner cube; `depth` from apex to the opening plane (mm).
    CornerCube {
        depth: f64,
    },
    Psd,
}

impl Kind {
    /// Its `kind` in a layout file.
    pub fn file_name(&self) -> &'static str {
        match self {
            Kind::Laser => "laser",
            Kind::Bs => "bs",
            Kind::Pbs => "pbs",
            Kind::Mirror => "mirror",
            Kind::Qwp => "qwp",
            Kind::CornerCube { .. } => "cc",
            Kind::Psd => "psd",
        }
    }
}

/// Which rigid body an element belongs to.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Module {
    /// Fixed modules 1 and 2 (on the machine bed).
    Fixed,
    /// Rides on the carriage: moves with travel and the six errors.
    Moving,
    /// Rides on the follower stage: translated by `d · follower_axis`.
    Follower,
}

/// Aperture of an element in its (u, v) plane.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Aperture {
    Circle { radius: f64 },
    Square { half: f64 },
}

impl Aperture {
    /// Whether the in-plane point (a, b) (mm) lies inside.
    #[inline]
    pub fn contains(&self, a: f64, b: f64) -> bool {
        match *self {
            Aperture::Circle { radius } => a * a + b * b <= radius * radius,
            Aperture::Square { half } => a.abs() <= half && b.abs() <= half,
        }
    }
}

/// A validated element.
#[derive(Clone, Debug, PartialEq)]
pub struct Element {
    pub name: String,
    pub kind: Kind,
    pub module: Module,
    pub frame: Frame,
    pub aperture: Aperture,
    /// PSD reading gains (X, Y); (1, 1) for everything else.
    pub gain: [f64; 2],
}

/// What a step does to the beam.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Action {
    Source,
    Transmit,
    Reflect,
    PbsTransmit,
    PbsReflect,
    Qwp,
    Retro,
    Detect,
}

impl Action {
    fn parse(s: &str) -> Option<Action> {
        Some(match s {
            "source" => Action::Source,
            "transmit" => Action::Transmit,
            "reflect" => Action::Reflect,
            "pbs_transmit" => Action::PbsTransmit,
            "pbs_reflect" => Action::PbsReflect,
            "qwp" => Action::Qwp,
            "retro" => Action::Retro,
            "detect" => Action::Detect,
            _ => return None,
        })
    }

    /// The name used in layout files.
    pub fn name(self) -> &'static str {
        match self {
            Action::Source => "source",
            Action::Transmit => "transmit",
            Action::Reflect => "reflect",
            Action::PbsTransmit => "pbs_transmit",
            Action::PbsReflect => "pbs_reflect",
            Action::Qwp => "qwp",
            Action::Retro => "retro",
            Action::Detect => "detect",
        }
    }

    fn fits(self, kind: Kind) -> bool {
        matches!(
            (self, kind),
            (Action::Source, Kind::Laser)
                | (Action::Transmit, Kind::Bs)
                | (Action::Reflect, Kind::Bs | Kind::Mirror)
                | (Action::PbsTransmit | Action::PbsReflect, Kind::Pbs)
                | (Action::Qwp, Kind::Qwp)
                | (Action::Retro, Kind::CornerCube { .. })
                | (Action::Detect, Kind::Psd)
        )
    }
}

/// Polarisation label of the beam (DESIGN §2): the laser is P; a quarter-wave plate turns
/// P→CP→S and S→CS→P.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Polarisation {
    P,
    Cp,
    S,
    Cs,
}

impl Polarisation {
    /// After one pass through a quarter-wave plate.
    pub fn after_qwp(self) -> Polarisation {
        match self {
            Polarisation::P => Polarisation::Cp,
            Polarisation::Cp => Polarisation::S,
            Polarisation::S => Polarisation::Cs,
            Polarisation::Cs => Polarisation::P,
        }
    }
    /// Short name.
    pub fn name(self) -> &'static str {
        match self {
            Polarisation::P => "P",
            Polarisation::Cp => "CP",
            Polarisation::S => "S",
            Polarisation::Cs => "CS",
        }
    }
}

/// One validated step: an element index and an action.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Step {
    pub element: usize,
    pub action: Action,
}

/// One validated path, ending on a PSD.
#[derive(Clone, Debug, PartialEq)]
pub struct OpticalPath {
    pub name: String,
    pub steps: Vec<Step>,
    /// Index of the PSD element it ends on.
    pub psd: usize,
}

/// A validated layout.
#[derive(Clone, Debug, PartialEq)]
pub struct Layout {
    pub name: String,
    /// Moving module reference point C (mm).
    pub c: V3,
    pub travel_axis: V3,
    pub follower_axis: V3,
    pub elements: Vec<Element>,
    /// The three paths in reading order.
    pub paths: [OpticalPath; 3],
    raw: RawLayout,
}

impl Layout {
    /// Read and validate a layout file.
    pub fn load(path: &FsPath) -> Result<Layout, LayoutError> {
        let label = path.display().to_string();
        let text = std::fs::read_to_string(path).map_err(|source| LayoutError::Io {
            path: label.clone(),
            source,
        })?;
        Layout::parse(&text, &label)
    }

    /// Parse and validate layout text; `label` names the source in errors.
    pub fn parse(text: &str, label: &str) -> Result<Layout, LayoutError> {
        let raw: RawLayout = toml::from_str(text).map_err(|e| LayoutError::Syntax {
            path: label.to_string(),
            message: crate::util::toml_error_line(text, &e),
        })?;
        Layout::validate(raw, label)
    }

    /// The built-in reference layout (`configs/optics/reference.toml`, compiled in).
    pub fn reference() -> Layout {
        Layout::parse(REFERENCE_TOML, "built-in reference layout")
            .expect("the shipped reference layout is valid (tested)")
    }

    /// The first stage as loaded (for hashing and re-serialising).
    pub fn raw(&self) -> &RawLayout {
        &self.raw
    }

    /// Index of an element by name.
    pub fn element_index(&self, name: &str) -> Option<usize> {
        self.elements.iter().position(|e| e.name == name)
    }

    /// A stable hash of the layout's content (CRC-64/XZ of its canonical JSON form), so a
    /// calibration can tell which layout it was made for. Whitespace and comments do not count.
    pub fn hash(&self) -> String {
        let canonical = serde_json::to_string(&self.raw).unwrap_or_default();
        let crc = crc::Crc::<u64>::new(&crc::CRC_64_XZ);
        format!("crc64:{:016x}", crc.checksum(canonical.as_bytes()))
    }

    /// A copy with element frames and PSD gains replaced (installation errors applied).
    pub fn with_elements(&self, elements: Vec<Element>) -> Layout {
        let mut out = self.clone();
        out.elements = elements;
        out
    }

    /// Second stage: validate.
    pub fn validate(raw: RawLayout, label: &str) -> Result<Layout, LayoutError> {
        let whole = |problem: String| LayoutError::whole(label, problem);
        let c = V3::from(raw.reference_point_mm);
        check_finite(&raw.reference_point_mm)
            .map_err(|_| whole("reference_point_mm has a non-finite value".into()))?;
        let travel_axis = unit_axis(raw.travel_axis).map_err(|p| {
            whole(format!(
                "travel_axis {p}: give a unit vector such as [0, 1, 0]"
            ))
        })?;
        let follower_axis = unit_axis(raw.follower_axis).map_err(|p| {
            whole(format!(
                "follower_axis {p}: give a unit vector such as [0, 1, 0]"
            ))
        })?;

        let mut elements = Vec::with_capacity(raw.elements.len());
        for re in &raw.elements {
            let el = validate_element(re)
                .map_err(|problem| LayoutError::element(label, &re.name, problem))?;
            if elements.iter().any(|e: &Element| e.name == el.name) {
                return Err(LayoutError::element(
                    label,
                    &re.name,
                    "the name is used twice: element names must be unique",
                ));
            }
            elements.push(el);
        }

        if raw.reading_paths.len() != 3 {
            return Err(whole(format!(
                "reading_paths lists {} paths: list exactly three (the paths giving X1/Y1, X2/Y2, X3/Y3)",
                raw.reading_paths.len()
            )));
        }
        let mut validated: Vec<OpticalPath> = Vec::with_capacity(3);
        for name in &raw.reading_paths {
            let rp = raw.paths.iter().find(|p| &p.name == name).ok_or_else(|| {
                whole(format!(
                    "reading_paths names path {name}, but no [[path]] has that name"
                ))
            })?;
            validated.push(validate_path(rp, &elements, label)?);
        }
        for rp in &raw.paths {
            if !raw.reading_paths.contains(&rp.name) {
                return Err(whole(format!(
                    "path {} is not in reading_paths: every path must give readings",
                    rp.name
                )));
            }
        }
        for (i, el) in elements.iter().enumerate() {
            if el.kind == Kind::Psd {
                let readers = validated.iter().filter(|p| p.psd == i).count();
                if readers == 0 {
                    return Err(LayoutError::element(
                        label,
                        &el.name,
                        "this PSD is missing from the paths: no path ends on it",
                    ));
                }
                if readers > 1 {
                    return Err(LayoutError::element(
                        label,
                        &el.name,
                        format!(
                            "{readers} paths end on this PSD: each PSD gives one path's readings"
                        ),
                    ));
                }
            }
        }
        let [p1, p2, p3]: [OpticalPath; 3] = validated
            .try_into()
            .map_err(|_| whole("internal: three paths expected".into()))?;
        Ok(Layout {
            name: raw.name.clone(),
            c,
            travel_axis,
            follower_axis,
            elements,
            paths: [p1, p2, p3],
            raw,
        })
    }
}

/// The reference layout shipped with the crate.
pub const REFERENCE_TOML: &str = include_str!("../../configs/optics/reference.toml");

fn check_finite(a: &[f64; 3]) -> Result<(), ()> {
    if a.iter().all(|x| x.is_finite()) {
        Ok(())
    } else {
        Err(())
    }
}

fn unit_axis(a: [f64; 3]) -> Result<V3, String> {
    let v = V3::from(a);
    if check_finite(&a).is_err() {
        return Err(format!("{} has a non-finite value", numbers(&a)));
    }
    if (v.norm() - 1.0).abs() > FRAME_TOL {
        return Err(format!("{} has length {:.9}, not 1", numbers(&a), v.norm()));
    }
    Ok(v)
}

fn validate_element(re: &RawElement) -> Result<Element, String> {
    let kind = match re.kind.as_str() {
        "laser" => Kind::Laser,
        "bs" => Kind::Bs,
        "pbs" => Kind::Pbs,
        "mirror" => Kind::Mirror,
        "qwp" => Kind::Qwp,
        "psd" => Kind::Psd,
        "cc" => {
            let depth = re
                .cc_depth_mm
                .ok_or("a corner cube needs cc_depth_mm (apex to opening plane, mm)".to_string())?;
            if !(depth.is_finite() && depth > 0.0) {
                return Err(format!("cc_depth_mm = {depth} must be positive"));
            }
            Kind::CornerCube { depth }
        }
        other => {
            return Err(format!(
                "kind \"{other}\" is unknown: use laser, bs, pbs, mirror, qwp, cc or psd"
            ));
        }
    };
    if re.cc_depth_mm.is_some() && !matches!(kind, Kind::CornerCube { .. }) {
        return Err("cc_depth_mm is only for corner cubes (kind = \"cc\")".into());
    }
    let module = match re.module.as_str() {
        "fixed1" | "fixed2" | "fixed" => Module::Fixed,
        "moving" => Module::Moving,
        "follower" => Module::Follower,
        other => {
            return Err(format!(
                "module \"{other}\" is unknown: use fixed1, fixed2, moving or follower"
            ));
        }
    };
    for (name, a) in [
        ("origin_mm", &re.origin_mm),
        ("u", &re.u),
        ("v", &re.v),
        ("n", &re.n),
    ] {
        check_finite(a).map_err(|_| format!("{name} {} has a non-finite value", numbers(a)))?;
    }
    let (u, v, n) = (V3::from(re.u), V3::from(re.v), V3::from(re.n));
    for (name, x) in [("u", u), ("v", v), ("n", n)] {
        if (x.norm() - 1.0).abs() > FRAME_TOL {
            return Err(format!(
                "frame is not orthonormal: |{name}| = {:.9}; u, v, n must be unit vectors",
                x.norm()
            ));
        }
    }
    for (name, d) in [("u·v", u.dot(&v)), ("u·n", u.dot(&n)), ("v·n", v.dot(&n))] {
        if d.abs() > FRAME_TOL {
            return Err(format!(
                "frame is not orthonormal: {name} = {d:.3e}; u, v, n must be at right angles"
            ));
        }
    }
    if (u.cross(&v) - n).norm() > FRAME_TOL {
        return Err("frame is left-handed: n must equal u × v".into());
    }
    if !(re.aperture_mm.is_finite() && re.aperture_mm > 0.0) {
        return Err(format!(
            "aperture_mm = {} must be positive (mm: circle radius or square half-size)",
            re.aperture_mm
        ));
    }
    let aperture = match re.aperture_shape.as_str() {
        "circle" => Aperture::Circle {
            radius: re.aperture_mm,
        },
        "square" => Aperture::Square {
            half: re.aperture_mm,
        },
        other => {
            return Err(format!(
                "aperture_shape \"{other}\" is unknown: use circle or square"
            ));
        }
    };
    let gain = match (re.gain, kind) {
        (None, _) => [1.0, 1.0],
        (Some(g), Kind::Psd) => {
            if !g.iter().all(|x| x.is_finite() && *x > 0.0) {
                return Err(format!("gain {} must be two positive numbers", numbers(&g)));
            }
            g
        }
        (Some(_), _) => return Err("gain is only for PSDs".into()),
    };
    Ok(Element {
        name: re.name.clone(),
        kind,
        module,
        frame: Frame::new(V3::from(re.origin_mm), u, v, n),
        aperture,
        gain,
    })
}

fn validate_path(
    rp: &RawPath,
    elements: &[Element],
    label: &str,
) -> Result<OpticalPath, LayoutError> {
    let step_err = |i: usize, el: &str, act: &str, problem: String| LayoutError::Invalid {
        path: label.to_string(),
        at: format!("path {} step {} ({el} {act}): ", rp.name, i + 1),
        problem,
    };
    if rp.steps.len() < 2 {
        return Err(LayoutError::whole(
            label,
            format!(
                "path {} has {} steps: a path runs from a laser source to a PSD detect step",
                rp.name,
                rp.steps.len()
            ),
        ));
    }
    let mut steps = Vec::with_capacity(rp.steps.len());
    let mut pol = Polarisation::P;
    let last = rp.steps.len() - 1;
    for (i, [el_name, act_name]) in rp.steps.iter().enumerate() {
        let element = elements
            .iter()
            .position(|e| &e.name == el_name)
            .ok_or_else(|| {
                step_err(
                    i,
                    el_name,
                    act_name,
                    "unknown element: no [[element]] has this name".into(),
                )
            })?;
        let action = Action::parse(act_name).ok_or_else(|| {
            step_err(i, el_name, act_name,
                "unknown action: use source, transmit, reflect, pbs_transmit, pbs_reflect, qwp, retro or detect".into())
        })?;
        let kind = elements[element].kind;
        if !action.fits(kind) {
            return Err(step_err(
                i,
                el_name,
                act_name,
                format!("a {} element cannot {act_name}", kind.file_name()),
            ));
        }
        if (i == 0) != (action == Action::Source) {
            return Err(step_err(
                i,
                el_name,
                act_name,
                "a path starts with one laser source step and has no other".into(),
            ));
        }
        if (i == last) != (action == Action::Detect) {
            return Err(step_err(
                i,
                el_name,
                act_name,
                "a path ends with one PSD detect step and has no other".into(),
            ));
        }
        match action {
            Action::Qwp => pol = pol.after_qwp(),
            Action::PbsTransmit if pol != Polarisation::P => {
                return Err(step_err(
                    i,
                    el_name,
                    act_name,
                    format!(
                        "a PBS transmits only P, but the beam is {} here: check the quarter-wave plate steps before it",
                        pol.name()
                    ),
                ));
            }
            Action::PbsReflect if pol != Polarisation::S => {
                return Err(step_err(
                    i,
                    el_name,
                    act_name,
                    format!(
                        "a PBS reflects only S, but the beam is {} here: check the quarter-wave plate steps before it",
                        pol.name()
                    ),
                ));
            }
            _ => {}
        }
        steps.push(Step { element, action });
    }
    Ok(OpticalPath {
        name: rp.name.clone(),
        psd: steps[last].element,
        steps,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn with_edit(f: impl FnOnce(&mut RawLayout)) -> Result<Layout, LayoutError> {
        let mut raw: RawLayout = toml::from_str(REFERENCE_TOML).unwrap();
        f(&mut raw);
        Layout::validate(raw, "test.toml")
    }

    #[test]
    fn reference_is_valid() {
        let l = Layout::reference();
        assert_eq!(l.elements.len(), 11);
        assert_eq!(l.paths[0].name, "P1");
        assert_eq!(l.elements[l.paths[1].psd].name, "PSD2");
        assert!(l.hash().starts_with("crc64:"));
    }

    #[test]
    fn non_orthonormal_frame_names_element() {
        let err = with_edit(|r| r.elements[1].u = [0.0, 0.1, 1.0]).unwrap_err();
        let s = err.to_string();
        assert!(s.contains("element BS1"), "{s}");
        assert!(s.contains("not orthonormal"), "{s}");
    }

    #[test]
    fn left_handed_frame_is_refused() {
        let err = with_edit(|r| {
            let n = r.elements[0].n;
            r.elements[0].n = [-n[0], -n[1], -n[2]];
        })
        .unwrap_err();
        assert!(err.to_string().contains("left-handed"), "{err}");
    }

    #[test]
    fn unknown_element_names_step() {
        let err = with_edit(|r| r.paths[0].steps[4][0] = "BS9".into()).unwrap_err();
        let s = err.to_string();
        assert!(
            s.contains("path P1 step 5 (BS9 reflect): unknown element"),
            "{s}"
        );
    }

    #[test]
    fn wrong_polarisation_at_pbs() {
        // Drop the second QWP pass on P1: the PBS then sees CP instead of S.
        let err = with_edit(|r| {
            r.paths[0].steps.remove(5);
        })
        .unwrap_err();
        let s = err.to_string();
        assert!(s.contains("PBS pbs_reflect"), "{s}");
        assert!(s.contains("reflects only S, but the beam is CP"), "{s}");
    }

    #[test]
    fn psd_missing_from_paths() {
        let err = with_edit(|r| {
            // P3 ends on PSD1 instead of PSD3: PSD3 is read by no path, PSD1 by two.
            let last = r.paths[2].steps.len() - 1;
            r.paths[2].steps[last][0] = "PSD1".into();
        })
        .unwrap_err();
        let s = err.to_string();
        assert!(s.contains("PSD1") || s.contains("PSD3"), "{s}");
    }

    #[test]
    fn action_must_fit_kind() {
        let err = with_edit(|r| r.paths[2].steps[3][1] = "reflect".into()).unwrap_err();
        assert!(err.to_string().contains("(CC reflect)"), "{err}");
    }

    #[test]
    fn syntax_error_names_line() {
        let err =
            Layout::parse("name = \"x\"\nreference_point_mm = [0, 0\n", "bad.toml").unwrap_err();
        let s = err.to_string();
        assert!(s.starts_with("layout bad.toml: line "), "{s}");
        assert!(!s.contains('\n'));
    }

    #[test]
    fn unknown_field_is_refused() {
        let text = REFERENCE_TOML.replacen("name = ", "colour = \"red\"\nname = ", 1);
        let err = Layout::parse(&text, "x.toml").unwrap_err();
        assert!(err.to_string().contains("colour"), "{err}");
    }

    #[test]
    fn hash_ignores_formatting_but_not_content() {
        let a = Layout::reference();
        let b = Layout::parse(&format!("# comment\n{REFERENCE_TOML}"), "b").unwrap();
        assert_eq!(a.hash(), b.hash());
        let c = with_edit(|r| r.elements[5].origin_mm[0] += 1.0).unwrap();
        assert_ne!(a.hash(), c.hash());
    }
}
