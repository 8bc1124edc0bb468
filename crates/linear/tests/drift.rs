//! Thermal drift during the step diagonal's runs: one-way it goes into the geometry; out and
//! back, each diagonal's drift rate is estimated with the geometry and separates from it.

use driftwatch_core::geometry::Vec3;
use driftwatch_linear::axis_errors::AxisErrors;
use driftwatch_linear::step_diagonal::{
    DIAGONALS, DiagonalRun, Estimate, Positioning, Setup, SolveError, conventional, from_csv,
    robust, simulate, to_csv,
};
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;

const RANGE: f64 = 120.0;
const SETUPS: usize = 150;

/// Median, 95th percentile and largest of the magnitudes.
fn stat(v: &[f64]) -> (f64, f64, f64) {
    let mut v: Vec<f64> = v.iter().map(|x| x.abs()).collect();
    v.sort_by(f64::total_cmp);
    (v[v.len() / 2], v[v.len() * 95 / 100], v[v.len() - 1])
}

fn rms(v: &[f64]) -> f64 {
    (v.iter().map(|x| x * x).sum::<f64>() / v.len() as f64).sqrt()
}

/// Squareness errors over the range, um.
fn square_errors(e: &Estimate, truth: &AxisErrors) -> [f64; 3] {
    std::array::from_fn(|i| (e.squareness_urad[i] - truth.squareness_urad[i]) * RANGE * 1e-3)
}

/// The forward leg of out-and-back runs: the one-way runs of the same readings.
fn forward(runs: &[DiagonalRun; 4], n: usize) -> [DiagonalRun; 4] {
    runs.clone().map(|r| DiagonalRun {
        signs: r.signs,
        readings_um: r.readings_um[..3 * n].to_vec(),
    })
}

/// Each diagonal's true drift along its beam (the mirror's tilt changes it by a cosine, 1e-8).
fn along_beams(d: &Vec3) -> [f64; 4] {
    DIAGONALS.map(|s| Vec3::new(s[0], s[1], s[2]).dot(d) / 3f64.sqrt())
}

struct Trial {
    errors: AxisErrors,
    setup: Setup,
    runs: [DiagonalRun; 4],
    pos: Positioning,
}

/// One machine and set-up (150 urad mirror tilts, 0.1 um noise, 5 s per move), measured out
/// and back with `drift`.
fn trial(rng: &mut ChaCha8Rng, drift: Vec3) -> Trial {
    let errors = AxisErrors::random(RANGE, rng);
    let mut setup = Setup::seed(150.0, rng);
    setup.drift_um_per_min = drift;
    setup.out_and_back = true;
    let (runs, pos) = simulate(&errors, &setup, rng);
    Trial {
        errors,
        setup,
        runs,
        pos,
    }
}

/// What 150 set-ups with a drift along Z of `rate` um/min show.
struct Case {
    /// |squareness error| over the range, median / 95 % / max, um: robust one-way (the forward
    /// legs) and out-and-back.
    one_way: (f64, f64, f64),
    oab: (f64, f64, f64),
    /// RMS of the out-and-back errors in their uncertainties: squareness, straightness at
    /// mid-range (in the profile's largest point sigma), drift rates.
    z_square: f64,
    z_straight: f64,
    z_rate: f64,
    /// |conventional out-and-back drift rate error|, median / 95 % / max, um/min.
    conv_rate: (f64, f64, f64),
}

fn drift_case(rate: f64, seed: u64) -> Case {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let drift = Vec3::new(0.0, 0.0, rate);
    let truth_rate = along_beams(&drift);
    let (mut one_way, mut oab, mut oab_z, mut str_z, mut rate_z, mut conv_oab) =
        (vec![], vec![], vec![], vec![], vec![], vec![]);
    let mut one_way_signed = [0.0; 3];
    for _ in 0..SETUPS {
        let t = trial(&mut rng, drift);
        let n = t.setup.steps;
        let ow = robust(&forward(&t.runs, n), &t.pos, &t.setup).unwrap();
        assert!(ow.drift_um_per_min.is_none());
        let r = robust(&t.runs, &t.pos, &t.setup).unwrap();
        let c = conventional(&t.runs, &t.setup).unwrap();
        for (i, e) in square_errors(&ow, &t.errors).iter().enumerate() {
            one_way.push(*e);
            one_way_signed[i] += e / SETUPS as f64;
        }
        for (i, e) in square_errors(&r, &t.errors).iter().enumerate() {
            oab.push(*e);
            oab_z.push(e / (r.squareness_sigma_urad[i] * RANGE * 1e-3));
        }
        // Every straightness profile at mid-range, in its largest point sigma.
        let mid = n / 2 - 1;
        let u = (mid + 1) as f64 * t.setup.step_mm;
        for k in 0..6 {
            let truth = t.errors.straightness[k].at(u, RANGE);
            str_z.push((r.straightness_um[k][mid] - truth) / r.straightness_sigma_um[k]);
        }
        let (est, sigma) = (
            r.drift_um_per_min.unwrap(),
            r.drift_sigma_um_per_min.unwrap(),
        );
        for d in 0..4 {
            rate_z.push((est[d] - truth_rate[d]) / sigma[d]);
        }
        // The conventional solve takes the drift out too; its rates against the truth.
        let cr = c.drift_um_per_min.unwrap();
        for d in 0..4 {
            conv_oab.push(cr[d] - truth_rate[d]);
        }
    }
    let case = Case {
        one_way: stat(&one_way),
        oab: stat(&oab),
        z_square: rms(&oab_z),
        z_straight: rms(&str_z),
        z_rate: rms(&rate_z),
        conv_rate: stat(&conv_oab),
    };
    let (ow, ob, cs) = (case.one_way, case.oab, case.conv_rate);
    println!(
        "{SETUPS} set-ups, {rate} um/min drift along Z (along the beams {truth_rate:.3?} um/min), |squareness error| over {RANGE} mm, median / 95 % / max:"
    );
    println!(
        "  robust one-way:      {:.2} / {:.2} / {:.2} um (mean signed X-Y {:.2}, X-Z {:.2}, Y-Z {:.2} um)",
        ow.0, ow.1, ow.2, one_way_signed[0], one_way_signed[1], one_way_signed[2]
    );
    println!(
        "  robust out-and-back: {:.3} / {:.3} / {:.3} um (RMS z {:.2})",
        ob.0, ob.1, ob.2, case.z_square
    );
    println!(
        "  out-and-back straightness at mid-range: RMS error / largest point sigma {:.2}",
        case.z_straight
    );
    println!(
        "  out-and-back drift rates: RMS z {:.2}; conventional out-and-back rates |error| {:.4} / {:.4} / {:.4} um/min",
        case.z_rate, cs.0, cs.1, cs.2
    );
    case
}

/// A drift along Z (the spindle growing) over runs of 3 min (6 min out and back): one-way it
/// biases the robust squareness by about the drift along the beam over a run (0.8 um over
/// 120 mm at 0.5 um/min, 3 um at 2 um/min); out and back the squareness is within its noise
/// and the same at both rates, the straightness within its sigma and the drift rates within
/// theirs.
#[test]
fn out_and_back_separates_a_drift_that_biases_the_one_way_squareness() {
    let slow = drift_case(0.5, 1919);
    let fast = drift_case(2.0, 1919);
    for c in [&slow, &fast] {
        // One-way, the drift is a bias several times the out-and-back error's spread ...
        assert!(
            c.one_way.0 > 3.0 * c.oab.1,
            "{:?} against {:?}",
            c.one_way,
            c.oab
        );
        // ... out and back, within about 1 um, and the uncertainties describe the spread.
        assert!(c.oab.2 < 1.0, "{:?}", c.oab);
        assert!(
            (c.z_square - 1.0).abs() < 0.2,
            "squareness RMS z {}",
            c.z_square
        );
        assert!(
            c.z_straight > 0.5 && c.z_straight < 1.15,
            "straightness {}",
            c.z_straight
        );
        assert!((c.z_rate - 1.0).abs() < 0.2, "drift RMS z {}", c.z_rate);
        // The conventional solve's rates: the same differences between the legs.
        assert!(c.conv_rate.1 < 0.03, "{:?}", c.conv_rate);
    }
    // The one-way bias grows with the rate (4 times the rate, about 4 times the bias); the
    // out-and-back error does not (the same set-ups and noise at both rates).
    let grow = fast.one_way.0 / slow.one_way.0;
    assert!(grow > 3.0 && grow < 5.0, "{grow}");
    assert!(fast.one_way.0 > 2.0, "{:?}", fast.one_way);
    assert!(
        (fast.oab.1 - slow.oab.1).abs() < 0.02,
        "{:?} {:?}",
        fast.oab,
        slow.oab
    );
}

/// Without drift, out and back agrees with one-way (the same forward readings): the squareness
/// differs by less than the one-way uncertainty, which the return leg shrinks; the estimated
/// drift rates are zero within their uncertainty.
#[test]
fn without_drift_out_and_back_agrees_with_one_way() {
    let mut rng = ChaCha8Rng::seed_from_u64(1920);
    let (mut diff_z, mut ratio, mut rate_z) = (vec![], vec![], vec![]);
    for _ in 0..SETUPS {
        let t = trial(&mut rng, Vec3::zeros());
        let n = t.setup.steps;
        let ow = robust(&forward(&t.runs, n), &t.pos, &t.setup).unwrap();
        let r = robust(&t.runs, &t.pos, &t.setup).unwrap();
        for i in 0..3 {
            diff_z
                .push((r.squareness_urad[i] - ow.squareness_urad[i]) / ow.squareness_sigma_urad[i]);
            ratio.push(r.squareness_sigma_urad[i] / ow.squareness_sigma_urad[i]);
        }
        let (rate, sigma) = (
            r.drift_um_per_min.unwrap(),
            r.drift_sigma_um_per_min.unwrap(),
        );
        for d in 0..4 {
            rate_z.push(rate[d] / sigma[d]);
        }
    }
    let (dz, rz) = (stat(&diff_z), rms(&rate_z));
    let (lo, hi) = ratio
        .iter()
        .fold((f64::MAX, f64::MIN), |(l, h), v| (l.min(*v), h.max(*v)));
    println!(
        "{SETUPS} set-ups without drift: |out-and-back - one-way| squareness in one-way sigmas median / 95 % / max {:.2} / {:.2} / {:.2}; sigma ratio out-and-back / one-way {lo:.3}..{hi:.3}; drift rates RMS z {rz:.2}",
        dz.0, dz.1, dz.2
    );
    assert!(dz.1 < 2.0, "{dz:?}");
    // Four more unknowns against 144 more readings: about as good, mostly better.
    assert!(lo < 0.97 && hi < 1.02, "{lo}..{hi}");
    assert!((rz - 1.0).abs() < 0.2, "{rz}");
}

/// An out-and-back log round-trips through CSV (the return leg as steps n+1..2n, Z, Y, X);
/// a log with one diagonal out and back and the others one-way is refused.
#[test]
fn out_and_back_logs_round_trip_and_are_detected() {
    let mut rng = ChaCha8Rng::seed_from_u64(45);
    let t = trial(&mut rng, Vec3::new(0.3, -0.2, 0.5));
    let n = t.setup.steps;
    let text = to_csv(&t.runs, &t.pos);
    assert!(text.contains(&format!("ppp,{},z,", n + 1)));
    assert!(text.contains(&format!("ppn,{},x,", 2 * n)));
    let (back, back_pos) = from_csv(&text, n).unwrap();
    assert_eq!(back[0].readings_um.len(), 6 * n);
    let a = robust(&t.runs, &t.pos, &t.setup).unwrap();
    let b = robust(&back, &back_pos, &t.setup).unwrap();
    for d in 0..4 {
        let (x, y) = (
            a.drift_um_per_min.unwrap()[d],
            b.drift_um_per_min.unwrap()[d],
        );
        assert!((x - y).abs() < 1e-3, "{x} {y}");
    }
    // The last return reading is at the start corner: only the drift over the whole run.
    let last = t.runs[0].readings_um[6 * n - 1];
    let expect = along_beams(&t.setup.drift_um_per_min)[0] * (6 * n) as f64 * 5.0 / 60.0;
    assert!((last - expect).abs() < 0.5, "{last} against {expect}");
    // Mixed legs: the file reads (one-way rows missing on the others is what it says) ...
    let mixed: String = text
        .lines()
        .filter(|l| {
            let mut c = l.split(',');
            let (d, s) = (c.next().unwrap(), c.next().unwrap());
            d == "diagonal" || d == "line" || d == "ppp" || s.parse::<usize>().unwrap() <= n
        })
        .map(|l| format!("{l}\n"))
        .collect();
    let e = from_csv(&mixed, n).unwrap_err().to_string();
    assert!(e.contains("npp step 13 z") && e.contains("missing"), "{e}");
    // ... and the solves refuse runs of different lengths.
    let mut runs = t.runs.clone();
    runs[2].readings_um.truncate(3 * n);
    assert!(matches!(
        robust(&runs, &t.pos, &t.setup),
        Err(SolveError::MixedLegs(..))
    ));
    // A step past 2n is refused by line.
    let bad = text.replacen(
        &format!("ppp,{},z,", n + 1),
        &format!("ppp,{},z,", 2 * n + 1),
        1,
    );
    assert!(
        from_csv(&bad, n)
            .unwrap_err()
            .to_string()
            .contains("is not 1..24")
    );
}

/// A one-way log in the layout written before the return leg existed still reads, as one-way:
/// two steps of 10 mm on a perfect machine (each reading `a / sqrt 3` per move), rows in the
/// file's order, the solve finding no squareness and estimating no drift.
#[test]
fn a_one_way_log_of_the_old_layout_still_reads() {
    let v = |k: usize| format!("{:.4}", k as f64 * 10_000.0 / 3f64.sqrt());
    let mut text = String::from("diagonal,step,axis,reading_um\n");
    for d in ["ppp", "npp", "pnp", "ppn"] {
        for m in 0..6 {
            text += &format!(
                "{d},{},{},{}\n",
                m / 3 + 1,
                ["x", "y", "z"][m % 3],
                v(m + 1)
            );
        }
    }
    for a in ["x", "y", "z"] {
        text += &format!("line,1,{a},0.0000\nline,2,{a},0.0000\n");
    }
    assert!(
        text.starts_with("diagonal,step,axis,reading_um\nppp,1,x,5773.5027\nppp,1,y,11547.0054\n")
    );
    let (runs, pos) = from_csv(&text, 2).unwrap();
    assert!(runs.iter().all(|r| r.readings_um.len() == 6));
    let mut setup = Setup::seed(0.0, &mut ChaCha8Rng::seed_from_u64(0));
    setup.steps = 2;
    let r = robust(&runs, &pos, &setup).unwrap();
    assert!(r.drift_um_per_min.is_none() && r.drift_sigma_um_per_min.is_none());
    for s in r.squareness_urad {
        assert!(s.abs() < 1e-3, "{s}");
    }
    // Written back, a one-way log is the same text.
    assert_eq!(to_csv(&runs, &pos), text);
}
