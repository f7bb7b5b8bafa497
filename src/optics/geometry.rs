//! Frames as homogeneous transforms and the moving-module transform (DESIGN §1).

use crate::units::Errors6;
use nalgebra::{Matrix3, Matrix4, Vector3};

/// A 3-vector in millimetres (points) or unitless (directions).
pub type V3 = Vector3<f64>;

/// An element's frame as the homogeneous matrix of the paper's eq. (1): columns u, v, n and the
/// origin o. `u`, `v` span the element's surface; `n` is its normal (laser: beam direction, corner
/// cube: the axis out of the opening).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Frame {
    m: Matrix4<f64>,
}

impl Frame {
    /// Frame from origin and axes (not checked here; `Layout` validates frames on load).
    pub fn new(o: V3, u: V3, v: V3, n: V3) -> Self {
        #[rustfmt::skip]
        let m = Matrix4::new(
            u.x, v.x, n.x, o.x,
            u.y, v.y, n.y, o.y,
            u.z, v.z, n.z, o.z,
            0.0, 0.0, 0.0, 1.0,
        );
        Frame { m }
    }

    /// The homogeneous matrix.
    pub fn matrix(&self) -> &Matrix4<f64> {
        &self.m
    }

    /// Origin o.
    #[inline]
    pub fn o(&self) -> V3 {
        V3::new(self.m[(0, 3)], self.m[(1, 3)], self.m[(2, 3)])
    }
    /// First in-plane axis u.
    #[inline]
    pub fn u(&self) -> V3 {
        V3::new(self.m[(0, 0)], self.m[(1, 0)], self.m[(2, 0)])
    }
    /// Second in-plane axis v.
    #[inline]
    pub fn v(&self) -> V3 {
        V3::new(self.m[(0, 1)], self.m[(1, 1)], self.m[(2, 1)])
    }
    /// Normal n.
    #[inline]
    pub fn n(&self) -> V3 {
        V3::new(self.m[(0, 2)], self.m[(1, 2)], self.m[(2, 2)])
    }

    /// This frame moved by the homogeneous transform `t` (points and directions alike).
    #[inline]
    pub fn transformed(&self, t: &Matrix4<f64>) -> Frame {
        Frame { m: t * self.m }
    }

    /// This frame translated by `delta` (orientation unchanged).
    #[inline]
    pub fn translated(&self, delta: V3) -> Frame {
        let mut m = self.m;
        m[(0, 3)] += delta.x;
        m[(1, 3)] += delta.y;
        m[(2, 3)] += delta.z;
        Frame { m }
    }

    /// This frame moved by `offset` given along its own (u, v, n) axes and rotated about its
    /// origin by `r_local` given in those axes: how an installation error is applied.
    pub fn perturbed(&self, offset: V3, r_local: &Matrix3<f64>) -> Frame {
        let axes = self.m.fixed_view::<3, 3>(0, 0);
        let rot = axes * r_local;
        let o = self.o() + axes * offset;
        Frame::new(
            o,
            rot.column(0).into(),
            rot.column(1).into(),
            rot.column(2).into(),
        )
    }
}

/// `Rz(c) · Ry(b) · Rx(a)`: rotation applying x first, then y, then z.
pub fn rot_zyx(a: f64, b: f64, c: f64) -> Matrix3<f64> {
    let (sa, ca) = a.sin_cos();
    let (sb, cb) = b.sin_cos();
    let (sc, cc) = c.sin_cos();
    #[rustfmt::skip]
    let m = Matrix3::new(
        cc * cb, cc * sb * sa - sc * ca, cc * sb * ca + sc * sa,
        sc * cb, sc * sb * sa + cc * ca, sc * sb * ca - cc * sa,
        -sb,     cb * sa,                cb * ca,
    );
    m
}

/// The moving module's homogeneous transform for errors `e` at nominal travel `travel`:
/// `p' = C + travel·axis + δ + R·(p − C)`, `R = Rz(ez)·Ry(ey)·Rx(ex)`.
pub fn module_transform(c: V3, travel_axis: V3, travel: f64, e: &Errors6) -> Matrix4<f64> {
    let r = rot_zyx(e.ex, e.ey, e.ez);
    let t = c + travel_axis * travel + V3::new(e.dx, e.dy, e.dz) - r * c;
    let mut m = Matrix4::identity();
    m.fixed_view_mut::<3, 3>(0, 0).copy_from(&r);
    m[(0, 3)] = t.x;
    m[(1, 3)] = t.y;
    m[(2, 3)] = t.z;
    m
}

#[cfg(test)]
mod tests {
    use super::*;

    fn rx(a: f64) -> Matrix3<f64> {
        Matrix3::new(1.0, 0.0, 0.0, 0.0, a.cos(), -a.sin(), 0.0, a.sin(), a.cos())
    }
    fn ry(a: f64) -> Matrix3<f64> {
        Matrix3::new(a.cos(), 0.0, a.sin(), 0.0, 1.0, 0.0, -a.sin(), 0.0, a.cos())
    }
    fn rz(a: f64) -> Matrix3<f64> {
        Matrix3::new(a.cos(), -a.sin(), 0.0, a.sin(), a.cos(), 0.0, 0.0, 0.0, 1.0)
    }

    #[test]
    fn rotation_order_is_x_first() {
        let (a, b, c) = (0.3, -0.2, 0.7);
        let expected = rz(c) * ry(b) * rx(a);
        assert!((rot_zyx(a, b, c) - expected).norm() < 1e-14);
    }

    #[test]
    fn module_transform_matches_definition() {
        let c = V3::new(1.0, 2.0, -3.0);
        let axis = V3::new(0.0, 1.0, 0.0);
        let e = Errors6 {
            dx: 0.01,
            dy: -0.02,
            dz: 0.03,
            ex: 1e-3,
            ey: -2e-3,
            ez: 3e-3,
        };
        let t = module_transform(c, axis, 50.0, &e);
        let p = V3::new(10.0, -20.0, 5.0);
        let hp = t * nalgebra::Vector4::new(p.x, p.y, p.z, 1.0);
        let r = rot_zyx(e.ex, e.ey, e.ez);
        let expected = c + axis * 50.0 + V3::new(e.dx, e.dy, e.dz) + r * (p - c);
        assert!((hp.xyz() - expected).norm() < 1e-12);
    }
}
