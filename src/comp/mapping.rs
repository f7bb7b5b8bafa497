//! Head frame → machine axes. The head's frame is fixed (x transverse, y along the travel,
//! z vertical, DESIGN §1); the axis under test may be the machine's X, Y or Z. A mapping says
//! which machine axis, with which sign, each head axis is; it must be a proper rotation
//! (orthogonal, right-handed), so translations and rotation vectors map the same way and the
//! ISO 230-1 names follow: translation along machine axis D of axis A is `E{D}{A}`, rotation
//! about X/Y/Z is `EA{A}`/`EB{A}`/`EC{A}` (for a Y axis with the standard mapping: dx→EXY,
//! dy→EYY, dz→EZY, ex→EAY, ey→EBY, ez→ECY).

use super::CompError;
use serde::{Deserialize, Serialize};
use std::fmt;
use std::str::FromStr;

/// A machine's linear axis.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, PartialOrd, Ord, Serialize, Deserialize)]
pub enum MachineAxis {
    X,
    Y,
    Z,
}

impl MachineAxis {
    pub const ALL: [MachineAxis; 3] = [MachineAxis::X, MachineAxis::Y, MachineAxis::Z];

    pub fn index(self) -> usize {
        self as usize
    }

    /// "X", "Y" or "Z".
    pub fn letter(self) -> &'static str {
        ["X", "Y", "Z"][self.index()]
    }

    /// The axis a letter names (either case, surrounding blanks ignored).
    pub fn from_letter(s: &str) -> Option<MachineAxis> {
        let s = s.trim();
        MachineAxis::ALL
            .into_iter()
            .find(|a| a.letter().eq_ignore_ascii_case(s))
    }

    /// The ISO 230-1 letter of a rotation about this axis: "A", "B" or "C".
    pub fn rotation_letter(self) -> &'static str {
        ["A", "B", "C"][self.index()]
    }
}

impl fmt::Display for MachineAxis {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.letter())
    }
}

/// A machine axis with a sign: "+X", "-Z".
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct SignedAxis {
    pub axis: MachineAxis,
    pub negative: bool,
}

impl SignedAxis {
    pub const fn plus(axis: MachineAxis) -> Self {
        SignedAxis {
            axis,
            negative: false,
        }
    }
    pub const fn minus(axis: MachineAxis) -> Self {
        SignedAxis {
            axis,
            negative: true,
        }
    }
    /// +1.0 or −1.0.
    pub fn sign(self) -> f64 {
        if self.negative { -1.0 } else { 1.0 }
    }
    fn vector(self) -> [i32; 3] {
        let mut v = [0; 3];
        v[self.axis.index()] = if self.negative { -1 } else { 1 };
        v
    }
    fn from_vector(v: [i32; 3]) -> Option<SignedAxis> {
        let k = v.iter().position(|&c| c != 0)?;
        Some(SignedAxis {
            axis: MachineAxis::ALL[k],
            negative: v[k] < 0,
        })
    }
}

impl fmt::Display for SignedAxis {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "{}{}", if self.negative { "-" } else { "+" }, self.axis)
    }
}

impl FromStr for SignedAxis {
    type Err = CompError;
    fn from_str(s: &str) -> Result<Self, CompError> {
        let t = s.trim();
        let (negative, rest) = match t.as_bytes().first() {
            Some(b'-') => (true, &t[1..]),
            Some(b'+') => (false, &t[1..]),
            _ => (false, t),
        };
        let axis = MachineAxis::from_letter(rest).ok_or_else(|| {
            CompError::Mapping(format!(
                "\"{s}\" is not a machine axis: give +X, -X, +Y, -Y, +Z or -Z"
            ))
        })?;
        Ok(SignedAxis { axis, negative })
    }
}

/// The ISO 230-1 name of one head DOF on the machine: `machine value = sign · head value`.
#[derive(Clone, Debug, PartialEq, Eq, Serialize)]
pub struct IsoName {
    /// E.g. "EXY".
    pub name: String,
    /// +1 or −1 (as an integer, to keep the name comparable).
    pub sign: i8,
    /// The machine axis the translation is along, or the rotation is about.
    pub along: MachineAxis,
}

/// A validated head → machine mapping.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize)]
pub struct AxisMapping {
    axis: MachineAxis,
    head: [SignedAxis; 3],
}

fn cross(a: [i32; 3], b: [i32; 3]) -> [i32; 3] {
    [
        a[1] * b[2] - a[2] * b[1],
        a[2] * b[0] - a[0] * b[2],
        a[0] * b[1] - a[1] * b[0],
    ]
}

impl AxisMapping {
    /// `axis` is the machine axis under test; `travel` is the head's y (`+axis` when the head
    /// travels towards increasing machine position); `head_x` and `head_z` the head's transverse
    /// and vertical axes. Refused unless the three are distinct axes forming a right-handed frame.
    pub fn new(
        axis: MachineAxis,
        travel: SignedAxis,
        head_x: SignedAxis,
        head_z: SignedAxis,
    ) -> Result<AxisMapping, CompError> {
        if travel.axis != axis {
            return Err(CompError::Mapping(format!(
                "the head's y (the travel) is {travel} but the axis under test is {axis}: give +{axis} or -{axis}"
            )));
        }
        if head_x.axis == axis || head_z.axis == axis || head_x.axis == head_z.axis {
            return Err(CompError::Mapping(format!(
                "head x = {head_x}, y = {travel}, z = {head_z}: each head axis must be a different machine axis"
            )));
        }
        let z_right = cross(head_x.vector(), travel.vector());
        if z_right != head_z.vector() {
            let want = SignedAxis::from_vector(z_right).map(|s| s.to_string());
            return Err(CompError::Mapping(format!(
                "head x = {head_x}, y = {travel}, z = {head_z} is left-handed: with these x and y, z must be {}",
                want.unwrap_or_default()
            )));
        }
        Ok(AxisMapping {
            axis,
            head: [head_x, travel, head_z],
        })
    }

    /// The usual mounting: travel along +axis; z vertical (+Z) unless the axis is Z itself,
    /// x completing a right-handed frame (for Z: x = +X, z = −Y).
    pub fn standard(axis: MachineAxis) -> AxisMapping {
        use MachineAxis::*;
        let (x, z) = match axis {
            X => (SignedAxis::minus(Y), SignedAxis::plus(Z)),
            Y => (SignedAxis::plus(X), SignedAxis::plus(Z)),
            Z => (SignedAxis::plus(X), SignedAxis::minus(Y)),
        };
        AxisMapping {
            axis,
            head: [x, SignedAxis::plus(axis), z],
        }
    }

    /// The machine axis under test.
    pub fn axis(&self) -> MachineAxis {
        self.axis
    }

    /// The machine axes of the head's x, y, z.
    pub fn head_axes(&self) -> [SignedAxis; 3] {
        self.head
    }

    /// ISO 230-1 names of the six DOFs in `Errors6` order.
    pub fn iso_names(&self) -> [IsoName; 6] {
        std::array::from_fn(|k| {
            let h = self.head[k % 3];
            let letter = if k < 3 {
                h.axis.letter()
            } else {
                h.axis.rotation_letter()
            };
            IsoName {
                name: format!("E{letter}{}", self.axis),
                sign: if h.negative { -1 } else { 1 },
                along: h.axis,
            }
        })
    }

    /// A head-frame vector (translation or small-rotation vector) in machine coordinates.
    pub fn to_machine(&self, v: [f64; 3]) -> [f64; 3] {
        let mut out = [0.0; 3];
        for (h, x) in self.head.iter().zip(v) {
            out[h.axis.index()] += h.sign() * x;
        }
        out
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use MachineAxis::*;

    fn names(m: &AxisMapping) -> Vec<String> {
        m.iso_names()
            .iter()
            .map(|n| format!("{}{}", if n.sign < 0 { "-" } else { "" }, n.name))
            .collect()
    }

    #[test]
    fn standard_names() {
        assert_eq!(
            names(&AxisMapping::standard(Y)),
            ["EXY", "EYY", "EZY", "EAY", "EBY", "ECY"]
        );
        // X axis: head x is −Y, so dx = −EYX and pitch (about head x) = −EBX.
        assert_eq!(
            names(&AxisMapping::standard(X)),
            ["-EYX", "EXX", "EZX", "-EBX", "EAX", "ECX"]
        );
        // Z axis: head z is −Y, so dz = −EYZ and yaw (about head z) = −EBZ.
        assert_eq!(
            names(&AxisMapping::standard(Z)),
            ["EXZ", "EZZ", "-EYZ", "EAZ", "ECZ", "-EBZ"]
        );
        for a in MachineAxis::ALL {
            let m = AxisMapping::standard(a);
            let [x, y, z] = m.head_axes();
            assert_eq!(AxisMapping::new(a, y, x, z), Ok(m), "{a}");
        }
    }

    #[test]
    fn sign_flips_and_validation() {
        // Head mounted upside down on a Y axis: x = −X, z = −Z (a rotation of 180° about y).
        let m = AxisMapping::new(
            Y,
            "+Y".parse().unwrap(),
            "-X".parse().unwrap(),
            "-z".parse().unwrap(),
        )
        .unwrap();
        assert_eq!(names(&m), ["-EXY", "EYY", "-EZY", "-EAY", "EBY", "-ECY"]);
        assert_eq!(m.to_machine([1.0, 2.0, 3.0]), [-1.0, 2.0, -3.0]);

        let e = AxisMapping::new(
            Y,
            SignedAxis::plus(Y),
            SignedAxis::plus(X),
            SignedAxis::minus(Z),
        )
        .unwrap_err();
        assert_eq!(
            e.to_string(),
            "axis mapping: head x = +X, y = +Y, z = -Z is left-handed: with these x and y, z must be +Z"
        );
        let e = AxisMapping::new(
            Y,
            SignedAxis::plus(Y),
            SignedAxis::plus(X),
            SignedAxis::plus(X),
        )
        .unwrap_err();
        assert!(e.to_string().contains("different machine axis"), "{e}");
        let e = AxisMapping::new(
            Y,
            SignedAxis::plus(X),
            SignedAxis::plus(Y),
            SignedAxis::plus(Z),
        )
        .unwrap_err();
        assert!(e.to_string().contains("axis under test is Y"), "{e}");
        assert!("W".parse::<SignedAxis>().is_err());
    }
}
