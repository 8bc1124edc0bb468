//! Statistics the checks and the diagnosis share: the chi-square distribution, the residual
//! tests of docs/physics.md 4.1 (Ljung-Box for serial correlation, a two-sided CUSUM for
//! a shift, partial correlation with a candidate driver), a robust scale (MAD) and the
//! selection arithmetic of section 4.3 (delta-BIC, the smallest detectable amplitude). Pure
//! code: plain slices in, numbers out.

use nalgebra::{DMatrix, DVector};

/// The chi-square quantile: the `x` with `P(chi2_dof <= x) = p`, to 1e-10 relative or better.
///
/// `p = 0` gives 0 and `p = 1` infinity; `p` outside `[0, 1]` or NaN, and `dof = 0` (no
/// distribution to test against), give NaN, which every caller here treats as a refusal.
pub fn chi2_quantile(p: f64, dof: usize) -> f64 {
    if dof == 0 || !(0.0..=1.0).contains(&p) {
        return f64::NAN;
    }
    if p == 0.0 {
        return 0.0;
    }
    if p == 1.0 {
        return f64::INFINITY;
    }
    let a = dof as f64 / 2.0;
    let ln_gamma_a = ln_gamma(a);
    // In the upper tail solve Q = 1 - p instead of P = p: 1 - p is exact there (Sterbenz) and Q
    // keeps its relative precision where P = 1 - Q would round it away.
    let upper = p > 0.5;
    let q_target = 1.0 - p;
    // Increasing in x in both forms, so the bracket logic is the same.
    let g = |x: f64| {
        let (pp, qq) = gamma_pq(a, x / 2.0, ln_gamma_a);
        if upper { q_target - qq } else { pp - p }
    };
    let density = |x: f64| 0.5 * ((a - 1.0) * (x / 2.0).ln() - x / 2.0 - ln_gamma_a).exp();

    let mut lo = 0.0_f64;
    let mut hi = (dof as f64).max(1.0);
    let mut guard = 0;
    while g(hi) < 0.0 {
        lo = hi;
        hi *= 2.0;
        guard += 1;
        if guard > 2000 || !hi.is_finite() {
            return f64::NAN;
        }
    }
    // Newton inside a shrinking bracket, falling back to bisection whenever Newton leaves it.
    let mut x = 0.5 * (lo + hi);
    for _ in 0..500 {
        let gx = g(x);
        if gx == 0.0 {
            return x;
        }
        if gx < 0.0 {
            lo = x;
        } else {
            hi = x;
        }
        let newton = x - gx / density(x);
        let next = if newton.is_finite() && newton > lo && newton < hi {
            newton
        } else {
            0.5 * (lo + hi)
        };
        let converged = (next - x).abs() <= 1e-14 * next.abs() || hi - lo <= 1e-14 * hi;
        x = next;
        if converged {
            break;
        }
    }
    x
}

/// ln Gamma(x) for x >= 0.5 (Lanczos, g = 7, 9 terms; about 1e-15 relative). The chi-square
/// uses only a = dof / 2 >= 0.5.
fn ln_gamma(x: f64) -> f64 {
    const G: f64 = 7.0;
    const C: [f64; 9] = [
        0.999_999_999_999_809_9,
        676.520_368_121_885_1,
        -1_259.139_216_722_402_8,
        771.323_428_777_653_1,
        -176.615_029_162_140_6,
        12.507_343_278_686_905,
        -0.138_571_095_265_720_12,
        9.984_369_578_019_572e-6,
        1.505_632_735_149_311_6e-7,
    ];
    let x = x - 1.0;
    let mut sum = C[0];
    for (i, c) in C.iter().enumerate().skip(1) {
        sum += c / (x + i as f64);
    }
    let t = x + G + 0.5;
    0.5 * (2.0 * std::f64::consts::PI).ln() + (x + 0.5) * t.ln() - t + sum.ln()
}

/// The regularized incomplete gamma functions `(P(a, x), Q(a, x))`: the series where it
/// converges fast (x < a + 1), the continued fraction otherwise (Numerical Recipes `gser` and
/// `gcf`); the other one is the complement, so each is computed where it is accurate.
fn gamma_pq(a: f64, x: f64, ln_gamma_a: f64) -> (f64, f64) {
    const EPS: f64 = 1e-16;
    const FPMIN: f64 = 1e-300;
    const MAX_ITER: usize = 100_000;
    if x <= 0.0 {
        return (0.0, 1.0);
    }
    let prefactor = (-x + a * x.ln() - ln_gamma_a).exp();
    if x < a + 1.0 {
        let mut ap = a;
        let mut del = 1.0 / a;
        let mut sum = del;
        for _ in 0..MAX_ITER {
            ap += 1.0;
            del *= x / ap;
            sum += del;
            if del.abs() < sum.abs() * EPS {
                break;
            }
        }
        let p = (sum * prefactor).min(1.0);
        (p, 1.0 - p)
    } else {
        // Modified Lentz.
        let mut b = x + 1.0 - a;
        let mut c = 1.0 / FPMIN;
        let mut d = 1.0 / b;
        let mut h = d;
        for i in 1..MAX_ITER {
            let an = -(i as f64) * (i as f64 - a);
            b += 2.0;
            d = an * d + b;
            if d.abs() < FPMIN {
                d = FPMIN;
            }
            c = b + an / c;
            if c.abs() < FPMIN {
                c = FPMIN;
            }
            d = 1.0 / d;
            let del = d * c;
            h *= del;
            if (del - 1.0).abs() < EPS {
                break;
            }
        }
        let q = (prefactor * h).min(1.0);
        (1.0 - q, q)
    }
}

/// The chi-square upper tail `P(chi2_dof > x)`; NaN for `dof = 0` or a NaN `x`.
pub fn chi2_sf(x: f64, dof: usize) -> f64 {
    if dof == 0 || x.is_nan() {
        return f64::NAN;
    }
    if x <= 0.0 {
        return 1.0;
    }
    if x.is_infinite() {
        return 0.0;
    }
    let a = dof as f64 / 2.0;
    gamma_pq(a, x / 2.0, ln_gamma(a)).1
}

/// The Ljung-Box test of a residual series for serial correlation up to `max_lag`.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize)]
pub struct LjungBox {
    pub q: f64,
    pub lags: usize,
    /// `P(chi2_lags > q)`: small when the residuals are correlated in time.
    pub p_value: f64,
}

/// `Q = n (n + 2) sum_k r_k^2 / (n - k)` over lags 1..=`max_lag` (fewer when the series is
/// short), against chi-square with that many degrees of freedom. `None` below 3 values or
/// for a constant series.
pub fn ljung_box(x: &[f64], max_lag: usize) -> Option<LjungBox> {
    let n = x.len();
    let lags = max_lag.min(n.saturating_sub(2));
    if n < 3 || lags == 0 {
        return None;
    }
    let mean = x.iter().sum::<f64>() / n as f64;
    let d: Vec<f64> = x.iter().map(|v| v - mean).collect();
    let c0: f64 = d.iter().map(|v| v * v).sum();
    if c0 <= 0.0 || !c0.is_finite() {
        return None;
    }
    let nf = n as f64;
    let q = nf
        * (nf + 2.0)
        * (1..=lags)
            .map(|k| {
                let ck: f64 = d[k..].iter().zip(&d).map(|(a, b)| a * b).sum();
                (ck / c0).powi(2) / (nf - k as f64)
            })
            .sum::<f64>();
    Some(LjungBox {
        q,
        lags,
        p_value: chi2_sf(q, lags),
    })
}

/// A two-sided tabular CUSUM of `x` around `target`.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize)]
pub struct Cusum {
    /// Index of the first value at which either sum passed the threshold.
    pub first_alarm: Option<usize>,
    /// Largest upper and lower sums reached.
    pub max_upper: f64,
    pub max_lower: f64,
}

/// `S+ = max(0, S+ + x - target - k)`, `S- = max(0, S- - x + target - k)`; an alarm when
/// either passes `h`. In units of the series (divide by its sigma first for the usual k = 0.5,
/// h = 5 of docs/physics.md 4.1).
pub fn cusum(x: &[f64], target: f64, k: f64, h: f64) -> Cusum {
    let (mut up, mut lo) = (0.0_f64, 0.0_f64);
    let mut out = Cusum {
        first_alarm: None,
        max_upper: 0.0,
        max_lower: 0.0,
    };
    for (i, v) in x.iter().enumerate() {
        up = (up + v - target - k).max(0.0);
        lo = (lo - v + target - k).max(0.0);
        out.max_upper = out.max_upper.max(up);
        out.max_lower = out.max_lower.max(lo);
        if out.first_alarm.is_none() && (up > h || lo > h) {
            out.first_alarm = Some(i);
        }
    }
    out
}

/// The partial correlation of `y` with a candidate driver `x`, given `controls`.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize)]
pub struct PartialCorrelation {
    pub r: f64,
    /// `r sqrt(dof / (1 - r^2))`, Student's t with `dof` degrees of freedom.
    pub t: f64,
    pub dof: usize,
}

/// Correlation of what is left of `y` and of `x` after least squares on the `controls` and an
/// intercept. `None` when the lengths differ, there are too few values, or either part left is
/// zero.
pub fn partial_correlation(
    y: &[f64],
    x: &[f64],
    controls: &[&[f64]],
) -> Option<PartialCorrelation> {
    let n = y.len();
    if x.len() != n || controls.iter().any(|c| c.len() != n) {
        return None;
    }
    let p = controls.len() + 1;
    let dof = n.checked_sub(p + 1).filter(|d| *d > 0)?;
    let z = DMatrix::from_fn(n, p, |i, j| if j == 0 { 1.0 } else { controls[j - 1][i] });
    let resid = |v: &[f64]| -> Option<DVector<f64>> {
        let v = DVector::from_column_slice(v);
        Some(crate::least_squares::residual_of(&z, &v))
    };
    let (ry, rx) = (resid(y)?, resid(x)?);
    let (syy, sxx) = (ry.dot(&ry), rx.dot(&rx));
    if syy <= 0.0 || sxx <= 0.0 {
        return None;
    }
    let r = (ry.dot(&rx) / (syy * sxx).sqrt()).clamp(-1.0, 1.0);
    let t = if r.abs() < 1.0 {
        r * (dof as f64 / (1.0 - r * r)).sqrt()
    } else {
        r.signum() * f64::INFINITY
    };
    Some(PartialCorrelation { r, t, dof })
}

/// The median of the finite values (`None` when there are none).
pub fn median(x: &[f64]) -> Option<f64> {
    let mut v: Vec<f64> = x.iter().copied().filter(|v| v.is_finite()).collect();
    if v.is_empty() {
        return None;
    }
    v.sort_by(f64::total_cmp);
    let m = v.len() / 2;
    Some(if v.len() % 2 == 1 {
        v[m]
    } else {
        0.5 * (v[m - 1] + v[m])
    })
}

/// A robust standard deviation: 1.4826 times the median absolute deviation (the normal
/// distribution's sigma when the data are normal, unmoved by a few outliers).
pub fn mad_sigma(x: &[f64]) -> Option<f64> {
    let m = median(x)?;
    let dev: Vec<f64> = x.iter().map(|v| (v - m).abs()).collect();
    median(&dev).map(|d| 1.4826 * d)
}

/// Delta-BIC of adding `delta_k` parameters that lower chi-square by `delta_chi2` over `n`
/// readings (sigma fixed): `delta_chi2 - delta_k ln n`; docs/physics.md 4.3 accepts at 10 or more.
pub fn delta_bic(delta_chi2: f64, delta_k: usize, n: usize) -> f64 {
    delta_chi2 - delta_k as f64 * (n.max(1) as f64).ln()
}

/// The smallest amplitude of a one-parameter signature that reaches delta-BIC 10 with 50 %
/// power (docs/physics.md 4.3): `sigma sqrt((10 + ln n) / (n (1 - R^2)))`, for readings of
/// standard uncertainty `sigma`, a signature of unit mean square over the `n` readings, and
/// `R^2` of the signature on what the model already has.
pub fn detection_threshold(sigma: f64, n: usize, r2: f64) -> f64 {
    let n = n.max(1) as f64;
    sigma * ((10.0 + n.ln()) / (n * (1.0 - r2))).sqrt()
}

/// The one-sided sign test at 5 %: the fewest wins of `n` paired comparisons (folds, or
/// later runs) that chance alone gives with probability at most 0.05; `None` when not even
/// `n` of `n` would (`n` < 5). A challenger replaces the textbook baseline only with that
/// many wins (7 of the 8 CV folds: P = 9/256 = 0.035; the folds overlap, so the true level
/// is somewhat higher, which errs towards the baseline).
pub fn sign_test_wins(n: usize) -> Option<usize> {
    // P(W >= w) for W ~ Binomial(n, 1/2), from the top down.
    let mut tail = 0.0;
    let mut c = 1.0; // C(n, k), k from n down
    let total = 2f64.powi(n as i32);
    let mut best = None;
    for k in (0..=n).rev() {
        tail += c / total;
        if tail > 0.05 {
            break;
        }
        best = Some(k);
        c = c * k as f64 / (n - k + 1) as f64;
    }
    best
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::SeedableRng;
    use rand_chacha::ChaCha8Rng;
    use rand_distr::{Distribution, StandardNormal};

    fn normal(n: usize, seed: u64) -> Vec<f64> {
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        (0..n).map(|_| StandardNormal.sample(&mut rng)).collect()
    }

    #[test]
    fn the_sign_test_asks_for_wins_chance_gives_under_five_percent() {
        assert_eq!(sign_test_wins(8), Some(7));
        assert_eq!(sign_test_wins(5), Some(5));
        assert_eq!(sign_test_wins(4), None);
        assert_eq!(sign_test_wins(10), Some(9));
        assert_eq!(sign_test_wins(20), Some(15));
    }

    #[test]
    fn chi2_quantiles_match_tables() {
        let cases = [
            (0.999, 4, 18.466_826_952_903),
            (0.999, 6, 22.457_744_484_825),
            (0.999, 16, 39.252_354_790_768),
            (0.95, 1, 3.841_458_820_694),
            (0.95, 10, 18.307_038_053_275),
            (0.99, 1, 6.634_896_601_021),
            (0.5, 1, 0.454_936_423_120),
            (0.999, 100, 149.449_252_779_038),
            (0.01, 5, 0.554_298),
            (0.975, 3, 9.348_404),
            (0.05, 10, 3.940_299),
        ];
        for (p, dof, want) in cases {
            let got = chi2_quantile(p, dof);
            assert!(
                (got - want).abs() < 1e-3,
                "p {p} dof {dof}: {got} vs {want}"
            );
        }
        // The values computed here to 12 digits (closed forms) hold to 1e-10 relative.
        for (p, dof, want) in &cases[..8] {
            let got = chi2_quantile(*p, *dof);
            assert!((got / want - 1.0).abs() < 1e-10, "p {p} dof {dof}: {got}");
        }
    }

    #[test]
    fn chi2_quantile_inverts_closed_forms_to_1e10() {
        // Two dof: an exponential of mean 2, q = -2 ln(1 - p).
        for p in [
            1e-9_f64,
            0.001,
            0.3,
            0.5,
            0.9,
            0.999,
            0.999_999,
            1.0 - 1e-12,
        ] {
            let want = -2.0 * (-p).ln_1p();
            let got = chi2_quantile(p, 2);
            assert!((got / want - 1.0).abs() < 1e-10, "p {p}: {got} vs {want}");
        }
        // Even dof: Q(x) = exp(-x/2) sum_{k < dof/2} (x/2)^k / k!.
        for dof in [4, 6, 16, 40] {
            for p in [0.01, 0.5, 0.999] {
                let x = chi2_quantile(p, dof);
                let (mut term, mut sum) = (1.0, 0.0);
                for k in 0..dof / 2 {
                    sum += term;
                    term *= x / 2.0 / (k + 1) as f64;
                }
                let q = (-x / 2.0).exp() * sum;
                assert!(
                    ((1.0 - q) - p).abs() < 1e-12,
                    "dof {dof} p {p}: P = {}",
                    1.0 - q
                );
            }
        }
    }

    #[test]
    fn chi2_quantile_edges() {
        assert_eq!(chi2_quantile(0.0, 3), 0.0);
        assert_eq!(chi2_quantile(1.0, 3), f64::INFINITY);
        assert!(chi2_quantile(f64::NAN, 3).is_nan());
        assert!(chi2_quantile(1.5, 3).is_nan());
        assert!(chi2_quantile(-0.1, 3).is_nan());
        assert!(chi2_quantile(0.5, 0).is_nan());
        // Increasing in p and in dof.
        assert!(chi2_quantile(0.9, 5) < chi2_quantile(0.99, 5));
        assert!(chi2_quantile(0.99, 5) < chi2_quantile(0.99, 6));
    }

    #[test]
    fn the_upper_tail_is_the_quantile_inverted() {
        for dof in [1, 2, 4, 10, 60] {
            for p in [0.01, 0.5, 0.95, 0.999] {
                let x = chi2_quantile(p, dof);
                assert!(
                    (chi2_sf(x, dof) - (1.0 - p)).abs() < 1e-10,
                    "dof {dof} p {p}"
                );
            }
        }
        assert_eq!(chi2_sf(0.0, 3), 1.0);
        assert_eq!(chi2_sf(f64::INFINITY, 3), 0.0);
        assert!(chi2_sf(1.0, 0).is_nan());
    }

    #[test]
    fn ljung_box_holds_its_size_on_white_noise_and_finds_an_ar1() {
        // 2000 white series of 200: about 5 % below p = 0.05.
        let rejected = (0..2000)
            .filter(|s| ljung_box(&normal(200, *s), 10).unwrap().p_value < 0.05)
            .count();
        assert!((60..=140).contains(&rejected), "{rejected} of 2000");
        // AR(1) with phi = 0.5.
        let e = normal(200, 7);
        let mut x = vec![0.0; 200];
        for i in 1..200 {
            x[i] = 0.5 * x[i - 1] + e[i];
        }
        let lb = ljung_box(&x, 10).unwrap();
        assert!(lb.p_value < 1e-6, "{lb:?}");
        assert!(ljung_box(&[1.0, 1.0, 1.0, 1.0], 2).is_none());
        assert!(ljung_box(&[1.0, 2.0], 5).is_none());
    }

    #[test]
    fn cusum_finds_a_step_and_stays_quiet_without_one() {
        let mut x = vec![0.0; 100];
        assert_eq!(cusum(&x, 0.0, 0.5, 5.0).first_alarm, None);
        for v in &mut x[50..] {
            *v = 2.0;
        }
        // 1.5 a step over the allowance: past 5 at the fourth shifted value.
        assert_eq!(cusum(&x, 0.0, 0.5, 5.0).first_alarm, Some(53));
        let neg: Vec<f64> = x.iter().map(|v| -v).collect();
        let c = cusum(&neg, 0.0, 0.5, 5.0);
        assert_eq!(c.first_alarm, Some(53));
        assert!(c.max_lower > 5.0 && c.max_upper == 0.0);
    }

    #[test]
    fn partial_correlation_sees_a_driver_and_not_its_shadow() {
        let (ez, ex, ey) = (normal(400, 1), normal(400, 2), normal(400, 3));
        // z drives y; x only follows z.
        let z: Vec<f64> = ez.clone();
        let x: Vec<f64> = z.iter().zip(&ex).map(|(z, e)| z + 0.3 * e).collect();
        let y: Vec<f64> = z.iter().zip(&ey).map(|(z, e)| 3.0 * z + 0.5 * e).collect();
        let raw = partial_correlation(&y, &x, &[]).unwrap();
        assert!(raw.t > 20.0, "{raw:?}");
        let given_z = partial_correlation(&y, &x, &[&z]).unwrap();
        assert!(given_z.t.abs() < 4.0, "{given_z:?}");
        assert_eq!(given_z.dof, 400 - 3);
        // And a real second driver is seen through the first.
        let y2: Vec<f64> = y.iter().zip(&ex).map(|(y, e)| y + 0.5 * e).collect();
        let seen = partial_correlation(&y2, &ex, &[&z]).unwrap();
        assert!(seen.t > 10.0, "{seen:?}");
        assert!(partial_correlation(&y, &x[..10], &[]).is_none());
    }

    #[test]
    fn mad_is_sigma_for_normal_data_and_ignores_outliers() {
        let mut x: Vec<f64> = normal(20000, 11).iter().map(|v| 2.0 * v).collect();
        let s = mad_sigma(&x).unwrap();
        assert!((s / 2.0 - 1.0).abs() < 0.03, "{s}");
        for v in x.iter_mut().take(200) {
            *v = 1e6;
        }
        let s = mad_sigma(&x).unwrap();
        assert!((s / 2.0 - 1.0).abs() < 0.05, "{s}");
        assert_eq!(median(&[3.0, 1.0, 2.0, f64::NAN]), Some(2.0));
        assert_eq!(median(&[]), None);
    }

    #[test]
    fn the_detection_threshold_is_the_worked_example_of_physics_4_3() {
        // sigma 0.5 um, 950 readings, a signature with R^2 = 0.74 on the baseline: 0.13 um.
        let a = detection_threshold(0.5, 950, 0.74);
        assert!((a - 0.1306).abs() < 5e-4, "{a}");
        assert!((delta_bic(30.0, 2, 1000) - (30.0 - 2.0 * 1000f64.ln())).abs() < 1e-12);
    }
}
