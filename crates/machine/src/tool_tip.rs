//! What the location errors do at the tool tip: the sensitivity of the tip's position to each
//! error at a reference pose, and the standard uncertainty of the tip that the thermal model's
//! predicted bands make there. The scheduler orders a cycle on that one number rather than on
//! each error's band, because a part sees the tip, not the errors: an uncertain error the
//! reference pose hardly feels costs no cycle, two moderate ones that add up at the tip do.

use std::collections::BTreeMap;

use driftwatch_core::geometry::Vec3;
use driftwatch_core::kinematics::Kinematics;
use driftwatch_thermal::model::{Prediction, Served};

use serde::{Deserialize, Serialize};

/// The reference tool-tip pose: a point on the table (mm, table frame) at a rotary pose (B, C
/// in deg, or the machine's own two rotary axes in that order) that every location error
/// reaches. `bench compensation` measures its residuals here too.
pub const REFERENCE_POINT_MM: [f64; 3] = [100.0, 100.0, 50.0];
pub const REFERENCE_POSE_DEG: [f64; 2] = [-45.0, 30.0];

/// The thermal model's predicted standard uncertainty of the tool tip at the reference pose
/// ([`uncertainty`]) at `t_ns`, and why it cannot be trusted, if it cannot.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct TipUncertainty {
    pub t_ns: i64,
    pub sigma_um: f64,
    pub untrusted: Option<String>,
}

/// The displacement of the tool tip (um) per unit (um or urad) of each identified error, at
/// the point `point_mm` and the rotary pose `pose_deg`. Central differences of one unit: the
/// errors are a few tens of units and their effect is linear at that size.
pub fn sensitivity(
    k: &Kinematics,
    point_mm: [f64; 3],
    pose_deg: [f64; 2],
) -> BTreeMap<String, [f64; 3]> {
    let nominal = k.nominal_state();
    let angles = k.angles_from_fields(pose_deg[0], pose_deg[1]);
    let p = Vec3::new(point_mm[0], point_mm[1], point_mm[2]);
    let tip = |delta: f64, id: driftwatch_core::kinematics::ErrorId| {
        let mut s = nominal;
        s.loc[id.axis][id.slot] += delta * id.scale();
        k.pose_transform(&s, &angles).point(&p)
    };
    k.identify_names()
        .into_iter()
        .filter_map(|name| {
            let id = k.error_id(&name)?;
            let d = (tip(1.0, id) - tip(-1.0, id)) * (1000.0 / 2.0);
            Some((name, [d.x, d.y, d.z]))
        })
        .collect()
}

/// The standard uncertainty of the tool tip (um, the root of the trace of its covariance:
/// the RMS length of its error) that `predictions` make through `sens`, the channels taken
/// as independent as the predictor runs them (one filter per error). Untrusted, with the
/// reason, when the model is `suspect`, an error is served from a fallback (its held-out
/// cycles scored the model worse than the last measured value, no change or the
/// regression: the band is then the fallback's held-out error and does not grow with the
/// time since the cycle) or an error has no usable prediction.
pub fn uncertainty(
    sens: &BTreeMap<String, [f64; 3]>,
    predictions: &[Prediction],
    suspect: Option<&str>,
    t_ns: i64,
) -> TipUncertainty {
    let mut var = 0.0;
    let mut untrusted = suspect.map(|why| format!("the model is suspect ({why})"));
    for (name, d) in sens {
        let p = predictions.iter().find(|p| &p.channel == name);
        match p {
            Some(p) if p.sigma.is_finite() && p.sigma >= 0.0 => {
                var += p.sigma.powi(2) * (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]);
                if p.source != Served::Model && untrusted.is_none() {
                    untrusted = Some(format!(
                        "{name} is served from its {} (the model did worse on its held-out cycles)",
                        p.source.as_str().replace('_', " ")
                    ));
                }
            }
            _ => {
                if untrusted.is_none() {
                    untrusted = Some(format!("{name} has no usable prediction"));
                }
            }
        }
    }
    TipUncertainty {
        t_ns,
        sigma_um: var.sqrt(),
        untrusted,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn pred(channel: &str, sigma: f64, source: Served) -> Prediction {
        Prediction {
            channel: channel.into(),
            value: 0.0,
            sigma,
            source,
            model_value: 0.0,
            no_change_value: 0.0,
            reason: None,
        }
    }

    #[test]
    fn the_sensitivity_matches_the_tip_moved_by_a_finite_error() {
        let k = Kinematics::load("table_bc").unwrap();
        let s = sensitivity(&k, REFERENCE_POINT_MM, REFERENCE_POSE_DEG);
        assert_eq!(s.len(), k.identify_names().len());
        let nominal = k.nominal_state();
        let angles = k.angles_from_fields(REFERENCE_POSE_DEG[0], REFERENCE_POSE_DEG[1]);
        let p = Vec3::new(100.0, 100.0, 50.0);
        let at_nominal = k.pose_transform(&nominal, &angles).point(&p);
        for (name, d) in &s {
            // Five units of the error alone, the tip's move in um, per unit.
            let id = k.error_id(name).unwrap();
            let mut st = nominal;
            st.loc[id.axis][id.slot] += 5.0 * id.scale();
            let moved = (k.pose_transform(&st, &angles).point(&p) - at_nominal) * (1000.0 / 5.0);
            let n = (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt();
            assert!(n > 1e-3, "{name}: the reference pose must feel it: {d:?}");
            for (m, x) in moved.iter().zip(d) {
                assert!((m - x).abs() < 1e-6 * n.max(1.0), "{name}: {d:?} {moved:?}");
            }
        }
        // A position error of the table's B axis moves the tip by (I - R) e: at B -45 deg
        // EZ0B moves it by 2 sin(22.5 deg).
        let ez = s["EZ0B"];
        let n = (ez[0] * ez[0] + ez[1] * ez[1] + ez[2] * ez[2]).sqrt();
        assert!(
            (n - 2.0 * 22.5_f64.to_radians().sin()).abs() < 1e-6,
            "{ez:?}"
        );
    }

    #[test]
    fn the_tip_band_adds_the_errors_bands_through_the_sensitivity() {
        let mut sens = BTreeMap::new();
        sens.insert("EX0B".to_string(), [1.0, 0.0, 0.0]);
        sens.insert("EA0B".to_string(), [0.0, 0.1, 0.0]);
        let preds = [
            pred("EX0B", 3.0, Served::Model),
            pred("EA0B", 40.0, Served::Model),
        ];
        let u = uncertainty(&sens, &preds, None, 7);
        assert!((u.sigma_um - 5.0).abs() < 1e-12, "{u:?}");
        assert_eq!((u.t_ns, u.untrusted), (7, None));
        // A fallback's band is its held-out error: not the model's to schedule on.
        let preds = [
            pred("EX0B", 3.0, Served::Model),
            pred("EA0B", 40.0, Served::LastMeasured),
        ];
        let u = uncertainty(&sens, &preds, None, 7);
        assert!(u.untrusted.unwrap().contains("EA0B"));
        // A suspect model and a missing error are untrusted too.
        let u = uncertainty(&sens, &preds[..1], Some("off by 9 sigma"), 7);
        assert!(u.untrusted.unwrap().contains("suspect"));
        let u = uncertainty(&sens, &preds[..1], None, 7);
        assert!(u.untrusted.unwrap().contains("EA0B has no usable"));
    }
}
