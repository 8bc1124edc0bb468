//! Rigid transforms in the machine frame: rotations (Rodrigues) and affine maps.
//!
//! Lengths are mm and angles rad inside the model; interfaces convert to um and urad.

use nalgebra::{Matrix3, Vector3};

pub type Vec3 = Vector3<f64>;
pub type Mat3 = Matrix3<f64>;

/// Right-handed rotation by `angle` (rad) about the unit vector `u` (Rodrigues).
pub fn rotation(u: &Vec3, angle: f64) -> Mat3 {
    let (s, c) = angle.sin_cos();
    let k = Mat3::new(0.0, -u.z, u.y, u.z, 0.0, -u.x, -u.y, u.x, 0.0);
    Mat3::identity() * c + k * s + (u * u.transpose()) * (1.0 - c)
}

/// An affine map `p -> r * p + t`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Affine {
    pub r: Mat3,
    pub t: Vec3,
}

impl Affine {
    pub fn identity() -> Self {
        Affine {
            r: Mat3::identity(),
            t: Vec3::zeros(),
        }
    }

    /// Rotation by `angle` about the line through `q` with unit direction `u`:
    /// `Tr(q) * Rot(u, angle) * Tr(-q)`.
    pub fn about_line(q: &Vec3, u: &Vec3, angle: f64) -> Self {
        let r = rotation(u, angle);
        Affine { r, t: q - r * q }
    }

    /// `self * other` (apply `other` first).
    pub fn then_inner(&self, other: &Affine) -> Affine {
        Affine {
            r: self.r * other.r,
            t: self.r * other.t + self.t,
        }
    }

    pub fn point(&self, p: &Vec3) -> Vec3 {
        self.r * p + self.t
    }

    pub fn vector(&self, v: &Vec3) -> Vec3 {
        self.r * v
    }
}

/// Angle in degrees reduced to (-180, 180], so that C = -270 and C = +90 give the same
/// floating-point pose.
pub fn wrap_deg(a: f64) -> f64 {
    if a > -180.0 && a <= 180.0 {
        return a;
    }
    let mut x = a % 360.0;
    if x <= -180.0 {
        x += 360.0;
    } else if x > 180.0 {
        x -= 360.0;
    }
    x
}

pub fn deg_to_rad(a: f64) -> f64 {
    wrap_deg(a).to_radians()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn rodrigues_matches_principal_rotations() {
        let a = 0.7;
        let rz = rotation(&Vec3::z(), a);
        let v = rz * Vec3::x();
        assert!((v - Vec3::new(a.cos(), a.sin(), 0.0)).norm() < 1e-15);
        let ry = rotation(&Vec3::y(), a);
        let v = ry * Vec3::z();
        assert!((v - Vec3::new(a.sin(), 0.0, a.cos())).norm() < 1e-15);
    }

    #[test]
    fn about_line_keeps_the_line_fixed() {
        let q = Vec3::new(1.0, 2.0, 3.0);
        let u = Vec3::new(0.1, 0.2, 1.0).normalize();
        let t = Affine::about_line(&q, &u, 1.3);
        let p = q + u * 5.0;
        assert!((t.point(&p) - p).norm() < 1e-12);
    }

    #[test]
    fn wrap_is_periodic() {
        assert_eq!(wrap_deg(-270.0), 90.0);
        assert_eq!(wrap_deg(270.0), -90.0);
        assert_eq!(wrap_deg(-180.0), 180.0);
        assert_eq!(wrap_deg(0.0), 0.0);
    }
}
