//! The R-test instrument: a master ball and a nest of three contact displacement sensors.
//!
//! One side of the machine carries the ball, the other the nest. Each sensor is a plunger that
//! moves along its stem direction `n` and touches the ball with a tip: a flat face (normal `m`,
//! ideally `n`) or a sphere. A reading is how far the plunger is pushed back from its zero,
//! positive when the ball centre moves along `n` towards the sensor.
//!
//! **The exact reading.** Ball centre `b` (nest frame, from the nest centre), ball radius `R`
//! with form error `f(u)` (radius minus `R` at outward direction `u`, in the ball's own frame):
//! - flat face: the face is the plane of normal `m` tangent to the ball, so the plunger stands
//!   at `s = (m.b + f(m) - f0) / (m.n)`. This is *exactly linear* in `b` for any displacement
//!   that keeps the contact on the face and within the stroke; what breaks the textbook form
//!   `s = n.b` is the face tilt (`m != n`: a gain `1/(m.n)` and a cross-axis sensitivity
//!   `m - n`), the gain of the scale, and the ball's form error where the contact point
//!   travels over the ball.
//! - sphere of radius `r`: the tip centre stays at distance `rho = R + r` from the ball centre,
//!   so `s = n.b + sqrt(rho^2 - |b_perp|^2) - rho`, with `b_perp` the part of `b` across the
//!   stem. The linear form is off by `|b_perp|^2 / (2 rho)`: 0.08 um at 50 um across with
//!   `rho` = 15 mm, 33 um at 1 mm.
//!
//! **Settings** (seed 002): E (the ETH/FIDIA nest on the table, sensors inclined alike below
//! the ball, one seen from +Z along +X), J (the nest on the table, sensors along machine X, Y,
//! Z), Es (the E nest on the spindle, one sensor seen from +Z along -X, the ball on the table).
//! The sensor-to-nest transform is the seed's equation (1), `(X,Y,Z) = Ry(phi) Rz(theta)
//! Rx(omega) (u,v,w)` with its matrices as printed (each the transpose of the active rotation)
//! and omega = 135 deg, phi = -35.264 deg, theta = 0 for E.
//!
//! **Calibration**: the linear axes move the ball by known steps along X, Y and Z; least
//! squares gives the 3 x 3 sensitivity matrix `G` (readings = `G b`), whose inverse is then
//! used instead of the design transform. It absorbs stem misalignment, face tilt and gains.

use driftwatch_core::geometry::{Mat3, Vec3, rotation};
use rand::Rng;
use rand_distr::{Distribution, StandardNormal};
use serde::{Deserialize, Serialize};

/// Where the nest and the ball are mounted, and how the sensors point.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub enum Setting {
    /// Nest on the table, sensors inclined (ETH Zurich / FIDIA), ball on the spindle.
    E,
    /// Nest on the table, sensors along machine X, Y, Z, ball on the spindle.
    J,
    /// The E nest on the spindle (IBS style), ball on the table.
    Es,
}

impl Setting {
    pub const ALL: [Setting; 3] = [Setting::E, Setting::J, Setting::Es];

    pub fn name(self) -> &'static str {
        match self {
            Setting::E => "E",
            Setting::J => "J",
            Setting::Es => "Es",
        }
    }

    pub fn parse(s: &str) -> Option<Setting> {
        match s.to_ascii_lowercase().as_str() {
            "e" => Some(Setting::E),
            "j" => Some(Setting::J),
            "es" => Some(Setting::Es),
            _ => None,
        }
    }

    /// Whether the nest turns with the table (E, J) or with the spindle head (Es).
    pub fn nest_on_table(self) -> bool {
        !matches!(self, Setting::Es)
    }

    /// The design stem directions, nest frame, one per column.
    pub fn design(self) -> Mat3 {
        match self {
            Setting::J => Mat3::identity(),
            Setting::E => seed_transform(135.0, -35.264, 0.0),
            // The same transform gives the same displacement from the spindle side: the
            // ball (on the table) moves against the tool, so each stem points the other way.
            Setting::Es => -seed_transform(135.0, -35.264, 0.0),
        }
    }
}

/// The seed's equation (1): `Ry(phi) Rz(theta) Rx(omega)` with the matrices as printed there.
pub fn seed_transform(omega_deg: f64, phi_deg: f64, theta_deg: f64) -> Mat3 {
    let (so, co) = omega_deg.to_radians().sin_cos();
    let (sp, cp) = phi_deg.to_radians().sin_cos();
    let (st, ct) = theta_deg.to_radians().sin_cos();
    let ry = Mat3::new(cp, 0.0, -sp, 0.0, 1.0, 0.0, sp, 0.0, cp);
    let rz = Mat3::new(ct, st, 0.0, -st, ct, 0.0, 0.0, 0.0, 1.0);
    let rx = Mat3::new(1.0, 0.0, 0.0, 0.0, co, so, 0.0, -so, co);
    ry * rz * rx
}

/// The sensor's tip.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub enum Tip {
    /// A flat face of this radius (mm): the contact must stay on it.
    Flat { radius_mm: f64 },
    /// A sphere of this radius (mm).
    Sphere { radius_mm: f64 },
}

/// One displacement sensor.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Sensor {
    /// Stem direction (unit, nest frame): positive readings push the plunger back along it.
    pub stem: Vec3,
    /// Face normal of a flat tip (unit, nest frame; `stem` when perpendicular).
    pub face: Vec3,
    /// Scale gain error (readings are multiplied by 1 + gain).
    pub gain: f64,
    pub tip: Tip,
    /// Stroke either way from the zero, mm.
    pub stroke_mm: f64,
}

/// The master ball's form: radius deviation, a smooth function of direction.
#[derive(Debug, Clone, PartialEq, Default, Serialize, Deserialize)]
pub struct BallForm {
    /// Coefficients (um) of [`form_basis`]; empty for a perfect sphere.
    pub coefficients: Vec<f64>,
}

impl BallForm {
    /// Radius deviation, um, at outward unit direction `u` (ball frame).
    pub fn deviation_um(&self, u: &Vec3) -> f64 {
        form_basis(u)
            .iter()
            .zip(&self.coefficients)
            .map(|(b, c)| b * c)
            .sum()
    }

    /// A random form of this sphericity on average (peak to valley, um; e.g. 0.13 um for
    /// a grade G5 ball, JIS B 1501, the seed's): independent normal coefficients on
    /// [`form_basis`], the same law the identification assumes for an unknown ball.
    pub fn random(sphericity_um: f64, rng: &mut impl Rng) -> BallForm {
        let sd = form_coefficient_sd(sphericity_um);
        BallForm {
            coefficients: (0..16)
                .map(|_| {
                    let z: f64 = StandardNormal.sample(rng);
                    sd * z
                })
                .collect(),
        }
    }
}

/// The basis the identification spans an unknown form with: the 16 monomials of degree 2
/// and 3 in the direction's components.
pub fn form_basis(u: &Vec3) -> [f64; 16] {
    let (x, y, z) = (u.x, u.y, u.z);
    [
        x * x,
        y * y,
        z * z,
        x * y,
        x * z,
        y * z,
        x * x * x,
        y * y * y,
        z * z * z,
        x * x * y,
        x * x * z,
        y * y * x,
        y * y * z,
        z * z * x,
        z * z * y,
        x * y * z,
    ]
}

/// The standard deviation of the [`form_basis`] coefficients (independent, equal) whose
/// forms have, on average, this sphericity (peak to valley), um. Deterministic.
pub fn form_coefficient_sd(sphericity_um: f64) -> f64 {
    use rand::SeedableRng;
    if sphericity_um <= 0.0 {
        return 0.0;
    }
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(16);
    let points = sphere_points(200);
    let draws = 200;
    let mut mean_pv = 0.0;
    for _ in 0..draws {
        let c: Vec<f64> = (0..16).map(|_| StandardNormal.sample(&mut rng)).collect();
        let (lo, hi) = points.iter().fold((f64::MAX, f64::MIN), |(l, h), u| {
            let v: f64 = form_basis(u).iter().zip(&c).map(|(b, c)| b * c).sum();
            (l.min(v), h.max(v))
        });
        mean_pv += (hi - lo) / draws as f64;
    }
    sphericity_um / mean_pv
}

/// Evenly spread unit vectors (Fibonacci sphere).
fn sphere_points(n: usize) -> Vec<Vec3> {
    let golden = std::f64::consts::PI * (3.0 - 5f64.sqrt());
    (0..n)
        .map(|i| {
            let z = 1.0 - 2.0 * (i as f64 + 0.5) / n as f64;
            let r = (1.0 - z * z).sqrt();
            let a = golden * i as f64;
            Vec3::new(r * a.cos(), r * a.sin(), z)
        })
        .collect()
}

fn random_unit(rng: &mut impl Rng) -> Vec3 {
    loop {
        let v = Vec3::new(
            StandardNormal.sample(rng),
            StandardNormal.sample(rng),
            StandardNormal.sample(rng),
        );
        if v.norm() > 1e-6 {
            return v.normalize();
        }
    }
}

/// A direction tilted from `d` by `angle` (rad) about a random axis across it.
fn tilted(d: &Vec3, angle: f64, rng: &mut impl Rng) -> Vec3 {
    let across = d.cross(&random_unit(rng));
    if across.norm() < 1e-9 || angle == 0.0 {
        return *d;
    }
    rotation(&across.normalize(), angle) * d
}

/// How an instrument departs from its design (each drawn per sensor), and its noise.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Imperfections {
    /// Stem direction off its design by up to this angle (uniform), deg.
    pub stem_deg: f64,
    /// Flat face off perpendicular to the stem by up to this angle (uniform), deg.
    pub face_deg: f64,
    /// Standard deviation of the scale gain error.
    pub gain_sd: f64,
    /// Ball sphericity (peak to valley), um.
    pub sphericity_um: f64,
}

impl Imperfections {
    /// The seed's device: misalignment within +-0.5 deg, HEIDENHAIN MT 1281 gauges (system
    /// accuracy +-0.2 um over 12 mm: a gain error of order 1e-4 is assumed), a G5 ball.
    pub fn seed() -> Self {
        Imperfections {
            stem_deg: 0.5,
            face_deg: 0.5,
            gain_sd: 1e-4,
            sphericity_um: 0.13,
        }
    }

    pub fn none() -> Self {
        Imperfections {
            stem_deg: 0.0,
            face_deg: 0.0,
            gain_sd: 0.0,
            sphericity_um: 0.0,
        }
    }
}

/// A whole R-test device as set up on a machine.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Instrument {
    pub setting: Setting,
    pub sensors: [Sensor; 3],
    pub ball_radius_mm: f64,
    pub form: BallForm,
    /// Reading noise, one standard deviation, um.
    pub noise_um: f64,
    /// Reading resolution (quantisation step), um; 0 for none.
    pub resolution_um: f64,
}

/// Why a reading could not be taken.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum ReadingError {
    #[error(
        "sensor {sensor}: the contact left the flat face ({lateral_mm:.3} mm across, face radius {radius_mm} mm)"
    )]
    OffFace {
        sensor: usize,
        lateral_mm: f64,
        radius_mm: f64,
    },
    #[error("the calibration moves do not span space")]
    Calibration,
    #[error("sensor {sensor}: {travel_mm:.3} mm is beyond the stroke of {stroke_mm} mm")]
    Stroke {
        sensor: usize,
        travel_mm: f64,
        stroke_mm: f64,
    },
}

impl Instrument {
    /// The device as designed: stems along the setting's design, flat faces of 4 mm radius,
    /// 12 mm stroke (the seed's MT 1281), a 12.7 mm ball radius, 0.05 um noise, 0.01 um steps.
    pub fn ideal(setting: Setting) -> Instrument {
        let d = setting.design();
        let sensor = |i: usize| {
            let n: Vec3 = d.column(i).into();
            Sensor {
                stem: n,
                face: n,
                gain: 0.0,
                tip: Tip::Flat { radius_mm: 4.0 },
                stroke_mm: 6.0,
            }
        };
        Instrument {
            setting,
            sensors: [sensor(0), sensor(1), sensor(2)],
            ball_radius_mm: 12.7,
            form: BallForm::default(),
            noise_um: 0.05,
            resolution_um: 0.01,
        }
    }

    /// A device of this setting with imperfections drawn from `rng`.
    pub fn drawn(setting: Setting, imp: &Imperfections, rng: &mut impl Rng) -> Instrument {
        let mut inst = Instrument::ideal(setting);
        for s in &mut inst.sensors {
            let a = imp.stem_deg.to_radians() * rng.random::<f64>();
            s.stem = tilted(&s.stem, a, rng);
            let f = imp.face_deg.to_radians() * rng.random::<f64>();
            s.face = tilted(&s.stem, f, rng);
            let z: f64 = StandardNormal.sample(rng);
            s.gain = imp.gain_sd * z;
        }
        if imp.sphericity_um > 0.0 {
            inst.form = BallForm::random(imp.sphericity_um, rng);
        }
        inst
    }

    /// The noiseless readings (um) for the ball centre at `b_mm` from the nest centre (nest
    /// frame), with `ball_to_nest` turning the ball's own frame into the nest frame (the form
    /// error is where the contact touches the ball). The readings are absolute: zero with the
    /// ball at the nest centre in its calibration orientation (the ball frame the nest frame).
    pub fn exact(&self, b_mm: &Vec3, ball_to_nest: &Mat3) -> Result<[f64; 3], ReadingError> {
        let mut out = [0.0; 3];
        for (i, s) in self.sensors.iter().enumerate() {
            // The contact's outward normal on the ball, in the ball's frame, now and at zero.
            let form_um = self.form.deviation_um(&(ball_to_nest.transpose() * s.face))
                - self.form.deviation_um(&s.face);
            let along = s.stem.dot(b_mm);
            let across = (b_mm - s.stem * along).norm();
            let travel_mm = match s.tip {
                Tip::Flat { radius_mm } => {
                    if across > radius_mm {
                        return Err(ReadingError::OffFace {
                            sensor: i + 1,
                            lateral_mm: across,
                            radius_mm,
                        });
                    }
                    (s.face.dot(b_mm) + form_um * 1e-3) / s.face.dot(&s.stem)
                }
                Tip::Sphere { radius_mm } => {
                    let rho = self.ball_radius_mm + radius_mm + form_um * 1e-3;
                    along + (rho * rho - across * across).max(0.0).sqrt() - rho
                }
            };
            if travel_mm.abs() > s.stroke_mm {
                return Err(ReadingError::Stroke {
                    sensor: i + 1,
                    travel_mm,
                    stroke_mm: s.stroke_mm,
                });
            }
            out[i] = travel_mm * 1e3 * (1.0 + s.gain);
        }
        Ok(out)
    }

    /// A reading as the device gives it: exact, plus noise, quantised to the resolution.
    pub fn read(
        &self,
        b_mm: &Vec3,
        ball_to_nest: &Mat3,
        rng: &mut impl Rng,
    ) -> Result<[f64; 3], ReadingError> {
        let mut r = self.exact(b_mm, ball_to_nest)?;
        for v in &mut r {
            let z: f64 = StandardNormal.sample(rng);
            *v += self.noise_um * z;
            if self.resolution_um > 0.0 {
                *v = (*v / self.resolution_um).round() * self.resolution_um;
            }
        }
        Ok(r)
    }

    /// The one-reading standard uncertainty, um: noise and quantisation.
    pub fn reading_sigma_um(&self) -> f64 {
        (self.noise_um.powi(2) + self.resolution_um.powi(2) / 12.0).sqrt()
    }
}

/// The sensor-to-nest transform a processing uses: readings `r` (um) -> ball centre `G^-1 r`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Calibration {
    pub setting: Setting,
    /// Sensitivity matrix: readings = `g` * displacement (nest frame), one row per sensor.
    pub g: Mat3,
    /// How it was obtained: "design" or "calibrated (...)".
    pub source: String,
    /// One-reading standard uncertainty, um.
    pub reading_sigma_um: f64,
    /// RMS residual of the calibration fit, um (0 for the design).
    pub residual_rms_um: f64,
    /// Covariance of each row of `G` (rows independent; dimensionless): after a calibration,
    /// its least-squares covariance `s^2 (D^T D)^-1`; for the design transform, the
    /// misalignment bound's rectangular variance `tan(bound)^2 / 3` on every element. It is
    /// systematic, common to every reading processed with `G`: the identification propagates
    /// it to the estimates, not reading by reading.
    pub row_cov: Mat3,
    /// The ball's sphericity (peak to valley, from its grade), um.
    pub sphericity_um: f64,
}

impl Calibration {
    /// The design transform alone (no calibration motion), for a device whose stems and
    /// faces are within `misalignment_deg` of their design and whose ball has this sphericity.
    pub fn design(
        setting: Setting,
        reading_sigma_um: f64,
        misalignment_deg: f64,
        sphericity_um: f64,
    ) -> Calibration {
        Calibration {
            setting,
            g: setting.design().transpose(),
            source: "design".into(),
            reading_sigma_um,
            residual_rms_um: 0.0,
            row_cov: Mat3::identity() * misalignment_deg.to_radians().tan().powi(2) / 3.0,
            sphericity_um,
        }
    }

    /// Ball centre displacement (um, nest frame) from readings (um).
    pub fn displacement(&self, r: &[f64; 3]) -> Option<Vec3> {
        self.g
            .try_inverse()
            .map(|gi| gi * Vec3::new(r[0], r[1], r[2]))
    }

    /// Covariance (um^2, nest frame) of one displacement read from the readings' noise,
    /// `G^-1 s^2 G^-T`. `G`'s own uncertainty (`row_cov`) and the ball's form are systematic:
    /// common to every reading, they are propagated to the estimates by the identification.
    pub fn displacement_cov(&self) -> Option<Mat3> {
        let gi = self.g.try_inverse()?;
        Some(gi * gi.transpose() * self.reading_sigma_um.powi(2))
    }
}

/// The calibration motion: the linear axes move the ball by `step_mm` along -X, +X, -Y, +Y,
/// -Z, +Z of the nest frame (`repeats` times each), the device reads, and least squares gives
/// `G`. `axis_error_ppm` is the linear axes' own scale error the calibration inherits.
/// `sphericity_um` is the ball's grade (what its certificate says), for the uncertainty.
pub fn calibrate(
    inst: &Instrument,
    step_mm: f64,
    repeats: usize,
    axis_error_ppm: f64,
    sphericity_um: f64,
    rng: &mut impl Rng,
) -> Result<Calibration, ReadingError> {
    let same = Mat3::identity();
    let mut rows = Vec::new();
    for _ in 0..repeats.max(1) {
        for axis in 0..3 {
            for sign in [-1.0, 1.0] {
                let mut cmd = Vec3::zeros();
                cmd[axis] = sign * step_mm;
                let actual = cmd * (1.0 + axis_error_ppm * 1e-6);
                let r = inst.read(&actual, &same, rng)?;
                rows.push((cmd * 1e3, r));
            }
        }
    }
    // readings_i = g_i . d: three independent least-squares fits on the same design, with
    // the one covariance `(D^T D)^-1`.
    let design = nalgebra::DMatrix::from_fn(rows.len(), 3, |i, j| rows[i].0[j]);
    let mut g = Mat3::zeros();
    let mut inv = Mat3::zeros();
    for k in 0..3 {
        let y = nalgebra::DVector::from_fn(rows.len(), |i, _| rows[i].1[k]);
        let fit = driftwatch_core::least_squares::lsq(&design, &y);
        if fit.rank < 3 {
            return Err(ReadingError::Calibration);
        }
        for j in 0..3 {
            g[(k, j)] = fit.beta[j];
            for l in 0..3 {
                inv[(j, l)] = fit.cov[(j, l)];
            }
        }
    }
    let ss: f64 = rows
        .iter()
        .map(|(d, r)| (Vec3::new(r[0], r[1], r[2]) - g * d).norm_squared())
        .sum();
    let dof = (rows.len() * 3).saturating_sub(9).max(1);
    Ok(Calibration {
        setting: inst.setting,
        g,
        source: format!(
            "calibrated ({} moves of {step_mm} mm along the linear axes)",
            rows.len()
        ),
        reading_sigma_um: inst.reading_sigma_um(),
        residual_rms_um: (ss / dof as f64).sqrt(),
        row_cov: inv * inst.reading_sigma_um().powi(2),
        sphericity_um,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::SeedableRng;
    use rand_chacha::ChaCha8Rng;

    #[test]
    fn the_e_setting_has_three_orthogonal_stems_alike_below_the_ball_one_along_plus_x() {
        let d = Setting::E.design();
        assert!((d.transpose() * d - Mat3::identity()).norm() < 1e-4);
        for i in 0..3 {
            // Each stem 35.26 deg below the horizontal: the contacts lie below the centre.
            assert!((d[(2, i)] + 1.0 / 3f64.sqrt()).abs() < 1e-4, "{d}");
        }
        // Sensor 1 seen from +Z lies along +X; Es's along -X (seed 002, 2.3).
        assert!(d[(0, 0)] > 0.8 && d[(1, 0)].abs() < 1e-9);
        assert!(Setting::Es.design()[(0, 0)] < -0.8);
        // Seen from +Z the three are 120 deg apart.
        let az: Vec<f64> = (0..3)
            .map(|i| d[(1, i)].atan2(d[(0, i)]).to_degrees())
            .collect();
        assert!(
            (az[1] + 120.0).abs() < 1e-3 && (az[2] - 120.0).abs() < 1e-3,
            "{az:?}"
        );
    }

    #[test]
    fn a_flat_tip_reads_exactly_linearly_and_a_sphere_loses_the_square_of_the_lateral_move() {
        let mut inst = Instrument::ideal(Setting::J);
        let id = Mat3::identity();
        let b = Vec3::new(0.05, -0.03, 0.02);
        let r = inst.exact(&b, &id).unwrap();
        assert!((r[0] - 50.0).abs() < 1e-9 && (r[1] + 30.0).abs() < 1e-9);
        inst.sensors[0].tip = Tip::Sphere { radius_mm: 2.0 };
        let r = inst.exact(&b, &id).unwrap();
        let rho: f64 = 14.7;
        let lat2 = 0.03f64.powi(2) + 0.02f64.powi(2);
        assert!(
            (r[0] - (50.0 - lat2 / (2.0 * rho) * 1e3)).abs() < 1e-4,
            "{r:?}"
        );
        // A face 0.5 deg off perpendicular: gain 1/cos and a cross sensitivity.
        inst.sensors[0].tip = Tip::Flat { radius_mm: 4.0 };
        inst.sensors[0].face = rotation(&Vec3::y(), 0.5f64.to_radians()) * Vec3::x();
        let r = inst.exact(&Vec3::new(0.0, 0.0, 0.05), &id).unwrap();
        assert!(
            (r[0] + 50.0 * 0.5f64.to_radians().tan()).abs() < 1e-6,
            "{r:?}"
        );
    }

    #[test]
    fn calibration_recovers_the_sensitivity_of_a_misaligned_device() {
        let mut rng = ChaCha8Rng::seed_from_u64(7);
        let inst = Instrument::drawn(Setting::E, &Imperfections::seed(), &mut rng);
        let cal = calibrate(&inst, 0.05, 3, 0.0, 0.13, &mut rng).unwrap();
        let b = Vec3::new(0.03, -0.02, 0.04);
        let id = Mat3::identity();
        let r = inst.exact(&b, &id).unwrap();
        let got = cal.displacement(&r).unwrap();
        assert!((got - b * 1e3).norm() < 0.05, "{got}");
        let design = Calibration::design(Setting::E, 0.05, 0.5, 0.13)
            .displacement(&r)
            .unwrap();
        assert!((design - b * 1e3).norm() > 0.1, "{design}");
    }
}
