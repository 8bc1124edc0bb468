//! Surrogate series for the diagnosis' tests of significance: a phase-randomised copy of a
//! series has the same amplitude spectrum (so the same slow wander) and random phases (so no
//! relation to anything else), the null a located term must beat.
//!
//! Pure and deterministic given the random source.

use rand::Rng;

/// `x` with the same amplitude spectrum and random phases (its mean kept).
pub fn phase_randomised(x: &[f64], rng: &mut impl Rng) -> Vec<f64> {
    use rustfft::{FftPlanner, num_complex::Complex};
    let n = x.len();
    if n < 4 {
        return x.to_vec();
    }
    let mean = x.iter().sum::<f64>() / n as f64;
    let mut buf: Vec<Complex<f64>> = x.iter().map(|v| Complex::new(v - mean, 0.0)).collect();
    let mut planner = FftPlanner::new();
    planner.plan_fft_forward(n).process(&mut buf);
    // A new phase for each frequency 1..n/2, its mirror the conjugate, so that the result
    // is real; the Nyquist term of an even n keeps its (real) value.
    for k in 1..n.div_ceil(2) {
        let turn = Complex::from_polar(1.0, rng.random::<f64>() * std::f64::consts::TAU);
        buf[k] *= turn;
        buf[n - k] = buf[k].conj();
    }
    planner.plan_fft_inverse(n).process(&mut buf);
    buf.iter().map(|c| mean + c.re / n as f64).collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::SeedableRng;
    use rand_chacha::ChaCha8Rng;

    #[test]
    fn a_phase_randomised_series_keeps_its_spectrum_and_loses_its_phase() {
        let mut rng = ChaCha8Rng::seed_from_u64(1);
        let x: Vec<f64> = (0..200)
            .map(|t| 20.0 + (t as f64 / 10.0).sin() + 0.3 * (t as f64 / 3.0).cos())
            .collect();
        let y = phase_randomised(&x, &mut rng);
        let mean = |v: &[f64]| v.iter().sum::<f64>() / v.len() as f64;
        let var = |v: &[f64]| {
            let m = mean(v);
            v.iter().map(|a| (a - m).powi(2)).sum::<f64>() / v.len() as f64
        };
        assert!((mean(&x) - mean(&y)).abs() < 1e-9);
        // Parseval: the same power.
        assert!(
            (var(&x) - var(&y)).abs() < 1e-9 * var(&x).max(1.0),
            "{} {}",
            var(&x),
            var(&y)
        );
        // Not the same series.
        let d: f64 = x.iter().zip(&y).map(|(a, b)| (a - b).powi(2)).sum();
        assert!(d > 1.0);
    }
}
