//! Plan design: a deterministic local search over measurement plans (poses, approaches,
//! repeats, order) for the plan with the smallest worst Cramer-Rao standard deviation of the
//! identified errors within a machine-time budget, refusing plans whose estimates a linear
//! in-cycle drift would bias (docs/physics.md 5.2).
//!
//! Every plan is judged as the service would solve it: `Plan::build`, the noise-free template
//! at the nominal state, `Identifier::new` with `SolveOptions::new(sigma)` (setter nuisances and
//! drift rates wherever the plan supports them) and `Identifier::cramer_rao`. A candidate that
//! does not build or cannot separate the errors is skipped, not an error.
//!
//! The drift alias of a plan is the least-squares bias `(J^T J)^-1 J^T d` of each identified
//! error for a tool-tip drift of 1 um/min along one machine axis, with `d` built as
//! `identify.rs` builds its drift columns: `-(t - t_ref)` in minutes for the readings along
//! that axis, 0 for the others. It vanishes when the plan estimates that axis' drift rate (the
//! column is then part of `J`) and nearly so for a time-symmetric order.

use std::collections::BTreeMap;

use nalgebra::{DMatrix, DVector};
use thiserror::Error;

use crate::geometry::wrap_deg;
use crate::identify::{Estimate, Identifier, Observation, SolveOptions, mean_time_ns};
use crate::kinematics::{AngleField, Kinematics};
use crate::measurement::Axis;
use crate::plan::{Order, Plan, PlanConfig, PoseConfig};

/// How the errors are compared with each other in the objective.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Weight {
    /// Each error in its own unit (um for positions, urad for orientations).
    Unit,
    /// Orientation errors as their effect at the tool tip: urad times a lever arm (mm) gives
    /// nm; the objective is in um throughout.
    Tip { lever_mm: f64 },
}

/// The largest drift alias a plan may have, per um/min of tool-tip drift.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum AliasLimit {
    /// This fraction of the plan's own worst sigma (objective units).
    Relative(f64),
    /// This many objective units (um or urad, or um at the tip).
    Absolute(f64),
}

/// Default of [`AliasLimit::Relative`]: a drift of 1 um/min, a brisk warm-up, may bias no
/// error by more than a tenth of the plan's worst sigma. On table_bc at 0.5 um the sequential
/// patent plan exceeds it 2.3 times (0.81 urad on EA0C per um/min along Z, against 0.35); the
/// time-symmetric one, which estimates the drift rates, is at 1e-8.
pub const DEFAULT_ALIAS_FRACTION: f64 = 0.1;

#[derive(Debug, Clone, PartialEq)]
pub struct DesignOptions {
    /// One-reading standard uncertainty, um.
    pub sigma_um: f64,
    pub weight: Weight,
    pub max_alias: AliasLimit,
    /// Machine-time budget, s; `None` for the reference plan's machine time.
    pub budget_s: Option<f64>,
    /// Largest `repeats` of a pose the search tries.
    pub max_repeats: u32,
    /// Hill-climbing steps per budget level, at most.
    pub max_steps: usize,
    /// Refuse plans that hold a nuisance the reference estimates (drift rates aside, which
    /// the alias covers). Without this the search prefers plans that cannot see the setter
    /// height or lateral shift: fewer parameters give smaller sigmas, but the errors then take
    /// any setter movement one-to-one (docs/physics.md 1.6).
    pub keep_reference_nuisances: bool,
}

impl DesignOptions {
    pub fn new(sigma_um: f64) -> Self {
        DesignOptions {
            sigma_um,
            weight: Weight::Unit,
            max_alias: AliasLimit::Relative(DEFAULT_ALIAS_FRACTION),
            budget_s: None,
            max_repeats: 4,
            max_steps: 60,
            keep_reference_nuisances: true,
        }
    }
}

#[derive(Debug, Clone, PartialEq, Error)]
pub enum DesignError {
    #[error("plan design: {0}")]
    BadOptions(String),
    #[error("the reference plan '{plan}' cannot be evaluated: {reason}")]
    Reference { plan: String, reason: String },
    #[error("machine '{machine}': no pose and approach of the search space builds into a plan")]
    NoCandidates { machine: String },
    #[error(
        "no plan within {budget_s:.1} s identifies the errors{}: {reason}",
        fastest_text(.fastest_s)
    )]
    Infeasible {
        budget_s: f64,
        /// Machine time of the fastest feasible plan the search found.
        fastest_s: Option<f64>,
        reason: String,
    },
}

fn fastest_text(f: &Option<f64>) -> String {
    f.map(|s| format!(" (the fastest plan found that does takes {s:.1} s)"))
        .unwrap_or_default()
}

/// The bias of every identified error per 1 um/min of tool-tip drift along one axis.
#[derive(Debug, Clone, PartialEq)]
pub struct DriftAlias {
    pub axis: Axis,
    /// Per identified error, in objective units per um/min (signed).
    pub bias: Vec<f64>,
}

/// One plan judged: its time, its Cramer-Rao sigmas and its drift alias.
#[derive(Debug, Clone)]
pub struct PlanEvaluation {
    pub config: PlanConfig,
    pub machine_time_s: f64,
    pub approaches: usize,
    /// `Identifier::cramer_rao` of the identified errors, in their units.
    pub sigmas: Vec<Estimate>,
    /// The same in objective units.
    pub weighted: Vec<f64>,
    pub worst: f64,
    pub worst_error: String,
    /// Unit of `worst` and of the alias.
    pub objective_unit: String,
    /// The nuisance parameters the solver estimates for this plan.
    pub nuisances: Vec<String>,
    pub alias: Vec<DriftAlias>,
    /// Largest `|bias|` over the errors and the axes, and where.
    pub max_alias: f64,
    pub max_alias_at: String,
    pub alias_limit: f64,
}

impl PlanEvaluation {
    /// Whether the drift alias is within its limit.
    pub fn alias_ok(&self) -> bool {
        self.max_alias <= self.alias_limit
    }

    /// The poses as `B0C0[z,lateral]x2` (the machine's axis names), in listed order, and
    /// the order.
    pub fn poses_text(&self, k: &Kinematics) -> String {
        let poses: Vec<String> = self
            .config
            .poses
            .iter()
            .map(|p| {
                let rep = if p.repeats > 1 {
                    format!("x{}", p.repeats)
                } else {
                    String::new()
                };
                let pose = k.pose_label(&k.angles_from_fields(p.b_deg, p.c_deg));
                format!("{pose}[{}]{rep}", p.approaches.join(","))
            })
            .collect();
        let order = match self.config.order {
            Order::TimeSymmetric => "time_symmetric",
            Order::AsListed => "as_listed",
        };
        format!("{order}: {}", poses.join(" "))
    }
}

/// Where the reference plan sits against the front.
#[derive(Debug, Clone)]
pub struct ReferencePosition {
    pub evaluation: PlanEvaluation,
    /// The front's worst sigma at the reference's machine time (the best front point that
    /// takes no longer), if any point does.
    pub front_worst_at_time: Option<f64>,
    /// Reference worst over that (1 = on the front).
    pub ratio: Option<f64>,
    /// The front's fastest plan reaching the reference's worst sigma, if any.
    pub front_time_at_worst: Option<f64>,
}

#[derive(Debug, Clone)]
pub struct PlanDesign {
    pub budget_s: f64,
    /// The best feasible plan within the budget.
    pub chosen: PlanEvaluation,
    /// Non-dominated feasible plans: machine time ascending, worst sigma strictly descending.
    pub front: Vec<PlanEvaluation>,
    pub reference: ReferencePosition,
    /// Candidate (pose, approach) units of the search space.
    pub units: usize,
    pub evaluated: usize,
    pub feasible: usize,
}

/// A candidate pose of the search space and the approaches that build there.
#[derive(Debug, Clone, PartialEq)]
pub struct CandidatePose {
    pub b_deg: f64,
    pub c_deg: f64,
    pub approaches: Vec<String>,
}

/// The approaches a pose is tried with: the patent's two, then the explicit directions
/// (which only add something where they differ from `lateral`, e.g. from inside the setter).
const APPROACHES: [&str; 8] = ["z", "lateral", "x+", "x-", "y+", "y-", "z+", "z-"];

/// Angles tried on the innermost axis: multiples of -45 deg (0 and the patent's -90 steps
/// first), shifted by +360 where the travel only allows positive angles.
const INNER_STEPS_DEG: [f64; 8] = [0.0, -45.0, -90.0, -135.0, -180.0, -225.0, -270.0, -315.0];
/// Angles tried on the outer axes (tilts).
const OUTER_DEG: [f64; 8] = [0.0, -45.0, 45.0, -90.0, 90.0, -135.0, 135.0, -180.0];

fn in_travel(a: f64, t: [f64; 2]) -> bool {
    a >= t[0] - 1e-9 && a <= t[1] + 1e-9
}

/// The pose fields (`b_deg`, `c_deg`) for angles of the outer axes (all at `outer`) and the
/// innermost axis, through each axis' message field, or `None` if two axes share a field with
/// different angles.
fn fields_for(k: &Kinematics, outer: f64, inner: f64) -> Option<(f64, f64)> {
    let n = k.rotary.len();
    let mut b: Option<f64> = None;
    let mut c: Option<f64> = None;
    for (i, ax) in k.rotary.iter().enumerate() {
        let a = if i + 1 == n { inner } else { outer };
        let slot = match ax.field {
            AngleField::B => &mut b,
            AngleField::C => &mut c,
        };
        match slot {
            Some(v) if (*v - a).abs() > 1e-9 => return None,
            _ => *slot = Some(a),
        }
    }
    Some((b.unwrap_or(0.0), c.unwrap_or(0.0)))
}

/// The candidate poses of a machine: each innermost-axis angle at each tilt of the outer
/// axes their travel allows, in the order a sequential plan would visit them (untilted first),
/// with the approaches that build at each (a single-pose plan through `Plan::build`).
pub fn candidate_poses(k: &Kinematics, base: &PlanConfig) -> Vec<CandidatePose> {
    let n = k.rotary.len();
    if n == 0 {
        return Vec::new();
    }
    let inner_travel = k.rotary[n - 1].travel_deg;
    let inner: Vec<f64> = INNER_STEPS_DEG
        .iter()
        .filter_map(|a| {
            [*a, a + 360.0]
                .into_iter()
                .find(|x| in_travel(*x, inner_travel))
        })
        .collect();
    let outer: Vec<f64> = if n == 1 {
        vec![0.0]
    } else {
        let mut v: Vec<f64> = OUTER_DEG
            .iter()
            .filter_map(|a| {
                // -180 and +180 are one pose: take whichever the travel allows.
                [*a, if *a == -180.0 { 180.0 } else { *a }]
                    .into_iter()
                    .find(|x| {
                        k.rotary[..n - 1]
                            .iter()
                            .all(|ax| in_travel(*x, ax.travel_deg))
                    })
            })
            .collect();
        v.dedup_by(|a, b| wrap_deg(*a - *b).abs() < 1e-9);
        v
    };
    let mut out = Vec::new();
    for o in &outer {
        for i in &inner {
            let Some((b_deg, c_deg)) = fields_for(k, *o, *i) else {
                continue;
            };
            let mut kept: Vec<(String, Vec<Observation>)> = Vec::new();
            for a in APPROACHES {
                let mut cfg = base.clone();
                cfg.order = Order::AsListed;
                cfg.poses = vec![PoseConfig {
                    b_deg,
                    c_deg,
                    approaches: vec![a.to_string()],
                    repeats: 1,
                }];
                let Ok(plan) = Plan::build(k, &cfg) else {
                    continue;
                };
                let Ok(obs) = plan.observations(k, &k.nominal_state()) else {
                    continue;
                };
                // An explicit direction that repeats `lateral` adds nothing.
                let same = |o: &[Observation]| {
                    o.len() == obs.len()
                        && o.iter().zip(&obs).all(|(p, q)| p.approach == q.approach)
                };
                if kept.iter().any(|(_, o)| same(o)) {
                    continue;
                }
                kept.push((a.to_string(), obs));
            }
            if !kept.is_empty() {
                out.push(CandidatePose {
                    b_deg,
                    c_deg,
                    approaches: kept.into_iter().map(|(a, _)| a).collect(),
                });
            }
        }
    }
    out
}

/// Judge one plan. `Err` with the reason if it does not build or cannot identify the errors.
pub fn evaluate(
    k: &Kinematics,
    cfg: &PlanConfig,
    opts: &DesignOptions,
) -> Result<PlanEvaluation, String> {
    let plan = Plan::build(k, cfg).map_err(|e| e.to_string())?;
    let obs = plan
        .observations(k, &k.nominal_state())
        .map_err(|e| e.to_string())?;
    let solve = SolveOptions::new(opts.sigma_um);
    let id = Identifier::new(k, &obs, &solve).map_err(|e| e.to_string())?;
    let all = id.cramer_rao(&obs).map_err(|e| e.to_string())?;
    let n_loc = k.identify.len();
    let sigmas: Vec<Estimate> = all.iter().take(n_loc).cloned().collect();
    let nuisances: Vec<String> = all.iter().skip(n_loc).map(|e| e.name.clone()).collect();
    let factor: Vec<f64> = k
        .identify
        .iter()
        .map(|id| match opts.weight {
            Weight::Tip { lever_mm } if !id.is_position() => lever_mm * 1e-3,
            _ => 1.0,
        })
        .collect();
    let weighted: Vec<f64> = sigmas
        .iter()
        .zip(&factor)
        .map(|(e, f)| e.sigma * f)
        .collect();
    let (wi, worst) = argmax(&weighted).ok_or("no identified errors")?;
    if !worst.is_finite() {
        return Err("the Cramer-Rao bound is not finite".into());
    }
    let design = id.nominal_design(&obs).map_err(|e| e.to_string())?;
    let alias = drift_alias(&design.sensitivity_um, &obs, n_loc)?
        .into_iter()
        .map(|(axis, b)| DriftAlias {
            axis,
            bias: b.iter().zip(&factor).map(|(x, f)| x * f).collect(),
        })
        .collect::<Vec<_>>();
    let mut max_alias = 0.0;
    let mut max_alias_at = String::new();
    for a in &alias {
        for (i, b) in a.bias.iter().enumerate() {
            if b.abs() > max_alias {
                max_alias = b.abs();
                max_alias_at = format!("{} from drift along {}", sigmas[i].name, a.axis.name());
            }
        }
    }
    let alias_limit = match opts.max_alias {
        AliasLimit::Relative(f) => f * worst,
        AliasLimit::Absolute(x) => x,
    };
    let objective_unit = match opts.weight {
        Weight::Unit => "um or urad",
        Weight::Tip { .. } => "um at the tip",
    };
    Ok(PlanEvaluation {
        config: cfg.clone(),
        machine_time_s: plan.machine_time_s,
        approaches: plan.steps.len(),
        worst_error: sigmas[wi].name.clone(),
        sigmas,
        weighted,
        worst,
        objective_unit: objective_unit.into(),
        nuisances,
        alias,
        max_alias,
        max_alias_at,
        alias_limit,
    })
}

fn argmax(v: &[f64]) -> Option<(usize, f64)> {
    v.iter()
        .copied()
        .enumerate()
        .fold(None, |acc: Option<(usize, f64)>, (i, x)| match acc {
            Some((_, m)) if m >= x => acc,
            _ => Some((i, x)),
        })
}

/// Bias of the first `n_loc` parameters per 1 um/min of drift along each machine axis some
/// reading moves along: `(J^T J)^-1 J^T d` (one sigma for all readings, so `W` cancels).
fn drift_alias(
    j: &DMatrix<f64>,
    obs: &[Observation],
    n_loc: usize,
) -> Result<Vec<(Axis, Vec<f64>)>, String> {
    let t_ref = mean_time_ns(obs.iter().map(|o| o.t_ns));
    // `(J^T J)^-1` once, for every axis' `d`.
    let fit = crate::least_squares::lsq(j, &DVector::zeros(j.nrows()));
    if fit.rank < j.ncols() {
        return Err("the information matrix is singular".into());
    }
    let inv = fit.cov;
    let mut out = Vec::new();
    for axis in [Axis::X, Axis::Y, Axis::Z] {
        if !obs.iter().any(|o| o.approach.axis == axis) {
            continue;
        }
        // As identify.rs: a drift rate v shifts a reading along its axis by -v (t - t_ref).
        let d = DVector::from_iterator(
            obs.len(),
            obs.iter().map(|o| {
                if o.approach.axis == axis {
                    -crate::units::ns_to_min(o.t_ns - t_ref)
                } else {
                    0.0
                }
            }),
        );
        let b = &inv * (j.transpose() * d);
        out.push((axis, b.iter().take(n_loc).copied().collect()));
    }
    Ok(out)
}

/// A point of the search space: for each chosen candidate pose (ascending index, so that
/// `as_listed` visits them in candidate order) its approaches as a bit mask over the pose's
/// approaches and its repeats; and whether the order is time-symmetric.
#[derive(Debug, Clone, PartialEq, Eq, PartialOrd, Ord)]
struct Genome {
    symmetric: bool,
    genes: Vec<(usize, u8, u32)>,
}

impl Genome {
    fn to_config(&self, base: &PlanConfig, poses: &[CandidatePose]) -> PlanConfig {
        let mut cfg = base.clone();
        cfg.name = "designed".into();
        cfg.description = "designed by `driftwatch plan design`".into();
        cfg.order = if self.symmetric {
            Order::TimeSymmetric
        } else {
            Order::AsListed
        };
        cfg.poses = self
            .genes
            .iter()
            .map(|(p, mask, repeats)| {
                let c = &poses[*p];
                PoseConfig {
                    b_deg: c.b_deg,
                    c_deg: c.c_deg,
                    approaches: c
                        .approaches
                        .iter()
                        .enumerate()
                        .filter(|(i, _)| mask & (1 << i) != 0)
                        .map(|(_, a)| a.clone())
                        .collect(),
                    repeats: *repeats,
                }
            })
            .collect();
        cfg
    }

    fn normalise(mut self) -> Self {
        self.genes.retain(|g| g.1 != 0);
        self.genes.sort();
        self
    }

    fn has_pose(&self, p: usize) -> bool {
        self.genes.iter().any(|g| g.0 == p)
    }
}

/// The reference plan as a genome, if its poses and approaches are all candidates.
fn genome_of(cfg: &PlanConfig, poses: &[CandidatePose]) -> Option<Genome> {
    let mut genes = Vec::new();
    for p in &cfg.poses {
        let i = poses.iter().position(|c| {
            wrap_deg(c.b_deg - p.b_deg).abs() < 1e-9 && wrap_deg(c.c_deg - p.c_deg).abs() < 1e-9
        })?;
        let mut mask = 0u8;
        for a in &p.approaches {
            mask |= 1 << poses[i].approaches.iter().position(|x| x == a)?;
        }
        genes.push((i, mask, p.repeats.max(1)));
    }
    Some(
        Genome {
            symmetric: cfg.order == Order::TimeSymmetric,
            genes,
        }
        .normalise(),
    )
}

/// The neighbours of a genome, in a fixed order: the other order; each pose's repeats one up
/// or down; each approach removed; each candidate approach added (to its pose, or as a new
/// pose at one repeat); each pose moved to another candidate pose one axis away.
fn neighbours(g: &Genome, poses: &[CandidatePose], max_repeats: u32) -> Vec<Genome> {
    let mut out = Vec::new();
    out.push(Genome {
        symmetric: !g.symmetric,
        genes: g.genes.clone(),
    });
    for (i, (_, mask, rep)) in g.genes.iter().enumerate() {
        for r in [rep.saturating_sub(1), rep + 1] {
            if r >= 1 && r <= max_repeats && r != *rep {
                let mut h = g.clone();
                h.genes[i].2 = r;
                out.push(h);
            }
        }
        for bit in 0..8 {
            if mask & (1 << bit) != 0 {
                let mut h = g.clone();
                h.genes[i].1 &= !(1 << bit);
                out.push(h.normalise());
            }
        }
    }
    for (p, c) in poses.iter().enumerate() {
        for bit in 0..c.approaches.len() {
            match g.genes.iter().position(|x| x.0 == p) {
                Some(i) if g.genes[i].1 & (1 << bit) == 0 => {
                    let mut h = g.clone();
                    h.genes[i].1 |= 1 << bit;
                    out.push(h);
                }
                Some(_) => {}
                None => {
                    let mut h = g.clone();
                    h.genes.push((p, 1 << bit, 1));
                    out.push(h.normalise());
                }
            }
        }
    }
    for (i, (p, mask, rep)) in g.genes.iter().enumerate() {
        let from = &poses[*p];
        for (q, to) in poses.iter().enumerate() {
            let one_axis_away = (to.b_deg == from.b_deg) != (to.c_deg == from.c_deg);
            if !one_axis_away || g.has_pose(q) {
                continue;
            }
            // Keep the approaches by name where the new pose has them.
            let mut m = 0u8;
            for (bit, a) in from.approaches.iter().enumerate() {
                if mask & (1 << bit) != 0
                    && let Some(j) = to.approaches.iter().position(|x| x == a)
                {
                    m |= 1 << j;
                }
            }
            if m != 0 {
                let mut h = g.clone();
                h.genes[i] = (q, m, *rep);
                out.push(h.normalise());
            }
        }
    }
    out
}

/// Ranking of a plan while climbing towards `budget_s`: first the time over the budget, then
/// the alias over its limit, then the worst sigma, then the time.
fn rank(e: &PlanEvaluation, budget_s: f64) -> [f64; 4] {
    [
        (e.machine_time_s - budget_s).max(0.0),
        (e.max_alias - e.alias_limit).max(0.0),
        e.worst,
        e.machine_time_s,
    ]
}

fn better(a: &[f64; 4], b: &[f64; 4]) -> bool {
    for (x, y) in a.iter().zip(b) {
        // Ties within rounding are ties, so that the walk never cycles on noise.
        if (x - y).abs() > 1e-9 * (1.0 + x.abs().max(y.abs())) {
            return x < y;
        }
    }
    false
}

struct Search<'a> {
    k: &'a Kinematics,
    base: &'a PlanConfig,
    poses: Vec<CandidatePose>,
    opts: &'a DesignOptions,
    /// Nuisances every plan must estimate.
    required: Vec<String>,
    archive: BTreeMap<Genome, Result<PlanEvaluation, String>>,
}

impl Search<'_> {
    fn eval(&mut self, g: &Genome) -> Result<PlanEvaluation, String> {
        if let Some(r) = self.archive.get(g) {
            return r.clone();
        }
        let r = if g.genes.is_empty() {
            Err("no poses".to_string())
        } else {
            evaluate(self.k, &g.to_config(self.base, &self.poses), self.opts).and_then(|e| {
                match self.required.iter().find(|n| !e.nuisances.contains(n)) {
                    Some(n) => Err(format!(
                        "the plan cannot estimate {n}, which the reference estimates"
                    )),
                    None => Ok(e),
                }
            })
        };
        self.archive.insert(g.clone(), r.clone());
        r
    }

    /// Best-improvement hill climbing from `start` under `budget_s`; the genome it ends on.
    fn climb(&mut self, start: Genome, budget_s: f64) -> Genome {
        let mut cur = start;
        let Ok(e) = self.eval(&cur) else {
            return cur;
        };
        let mut cur_rank = rank(&e, budget_s);
        for _ in 0..self.opts.max_steps {
            let mut best: Option<(Genome, [f64; 4])> = None;
            for h in neighbours(&cur, &self.poses, self.opts.max_repeats) {
                let Ok(e) = self.eval(&h) else { continue };
                let r = rank(&e, budget_s);
                if best.as_ref().is_none_or(|(_, b)| better(&r, b)) {
                    best = Some((h, r));
                }
            }
            match best {
                Some((h, r)) if better(&r, &cur_rank) => {
                    cur = h;
                    cur_rank = r;
                }
                _ => break,
            }
        }
        cur
    }
}

/// Budget levels the search climbs to, as fractions of the budget: the budget itself for the
/// chosen plan, then shorter ones so that the front reaches down to the fastest plans.
const LEVELS: [f64; 5] = [1.0, 0.8, 0.6, 0.45, 0.3];

/// Design a plan for machine `k`: probing parameters (feed, dwell, clearance, ...) as in
/// `reference`, which also sets the default budget and is placed against the front.
pub fn design(
    k: &Kinematics,
    reference: &PlanConfig,
    opts: &DesignOptions,
) -> Result<PlanDesign, DesignError> {
    if !(opts.sigma_um > 0.0 && opts.sigma_um.is_finite()) {
        return Err(DesignError::BadOptions(
            "sigma_um must be a positive number".into(),
        ));
    }
    if let Weight::Tip { lever_mm } = opts.weight
        && !(lever_mm > 0.0 && lever_mm.is_finite())
    {
        return Err(DesignError::BadOptions(
            "the lever arm must be a positive number of mm".into(),
        ));
    }
    match opts.max_alias {
        AliasLimit::Relative(x) | AliasLimit::Absolute(x) if !(x >= 0.0 && x.is_finite()) => {
            return Err(DesignError::BadOptions(
                "the alias limit must be a non-negative number".into(),
            ));
        }
        _ => {}
    }
    if opts.max_repeats == 0 {
        return Err(DesignError::BadOptions(
            "max_repeats must be at least 1".into(),
        ));
    }
    let ref_eval = evaluate(k, reference, opts).map_err(|reason| DesignError::Reference {
        plan: reference.name.clone(),
        reason,
    })?;
    let budget_s = opts.budget_s.unwrap_or(ref_eval.machine_time_s);
    if !(budget_s > 0.0 && budget_s.is_finite()) {
        return Err(DesignError::BadOptions(
            "the budget must be a positive number of seconds".into(),
        ));
    }
    let poses = candidate_poses(k, reference);
    if poses.is_empty() {
        return Err(DesignError::NoCandidates {
            machine: k.name.clone(),
        });
    }
    let units = poses.iter().map(|p| p.approaches.len()).sum();
    let mut s = Search {
        k,
        base: reference,
        poses,
        opts,
        required: if opts.keep_reference_nuisances {
            ref_eval
                .nuisances
                .iter()
                .filter(|n| !n.starts_with("tool_drift"))
                .cloned()
                .collect()
        } else {
            Vec::new()
        },
        archive: BTreeMap::new(),
    };
    // Seeds: the reference in both orders.
    let mut seeds = Vec::new();
    if let Some(g) = genome_of(reference, &s.poses) {
        seeds.push(Genome {
            symmetric: !g.symmetric,
            genes: g.genes.clone(),
        });
        seeds.push(g);
    }
    // Down the levels, each from the seeds and every plan the level above ended on; then back
    // up to the budget from every end (a short plan grown back can beat a long one pruned).
    let mut ends: Vec<Genome> = Vec::new();
    for f in LEVELS {
        let level = budget_s * f;
        let starts: Vec<Genome> = seeds.iter().chain(&ends).cloned().collect();
        for g in starts {
            ends.push(s.climb(g, level));
        }
        ends.sort();
        ends.dedup();
    }
    for g in ends {
        s.climb(g, budget_s);
    }
    let feasible: Vec<&PlanEvaluation> = s
        .archive
        .values()
        .filter_map(|r| r.as_ref().ok())
        .filter(|e| e.alias_ok())
        .collect();
    let front = pareto_front(&feasible);
    let chosen = feasible
        .iter()
        .filter(|e| e.machine_time_s <= budget_s)
        .min_by(|a, b| {
            a.worst
                .total_cmp(&b.worst)
                .then(a.machine_time_s.total_cmp(&b.machine_time_s))
        })
        .map(|e| (*e).clone());
    let Some(chosen) = chosen else {
        let fastest_s = feasible
            .iter()
            .map(|e| e.machine_time_s)
            .min_by(f64::total_cmp);
        return Err(DesignError::Infeasible {
            budget_s,
            fastest_s,
            reason: infeasible_reason(&s.archive, budget_s),
        });
    };
    let reference = place(ref_eval, &front);
    Ok(PlanDesign {
        budget_s,
        chosen,
        front,
        reference,
        units,
        evaluated: s.archive.len(),
        feasible: feasible.len(),
    })
}

/// Why nothing within the budget qualifies: the identifiability refusal of the fastest plan
/// within it that the search tried, else the alias or the time.
fn infeasible_reason(
    archive: &BTreeMap<Genome, Result<PlanEvaluation, String>>,
    budget_s: f64,
) -> String {
    let within_alias = archive
        .values()
        .filter_map(|r| r.as_ref().ok())
        .filter(|e| e.machine_time_s <= budget_s)
        .min_by(|a, b| a.machine_time_s.total_cmp(&b.machine_time_s));
    if let Some(e) = within_alias {
        return format!(
            "the plans that fit alias in-cycle drift, e.g. {:.1} s with {:.3} {} per um/min on {} (limit {:.3})",
            e.machine_time_s, e.max_alias, e.objective_unit, e.max_alias_at, e.alias_limit
        );
    }
    // Every identifiable plan the search met is too slow; name what the fast ones lack.
    let refusal = archive.values().find_map(|r| match r {
        Err(m) if m.contains("cannot separate") || m.contains("cannot determine") => {
            Some(m.clone())
        }
        _ => None,
    });
    match refusal {
        Some(m) => format!("removing more poses or approaches leaves plans that fail: {m}"),
        None => "every plan the search built takes longer".into(),
    }
}

/// The non-dominated plans: sorted by machine time, each with a strictly smaller worst sigma
/// than every faster one.
pub fn pareto_front(plans: &[&PlanEvaluation]) -> Vec<PlanEvaluation> {
    let mut v: Vec<&PlanEvaluation> = plans.to_vec();
    v.sort_by(|a, b| {
        a.machine_time_s
            .total_cmp(&b.machine_time_s)
            .then(a.worst.total_cmp(&b.worst))
    });
    let mut out: Vec<PlanEvaluation> = Vec::new();
    for e in v {
        // Better than every faster plan by more than 1e-4 of its sigma: finite differences
        // leave the sigmas of equivalent plans (the same touches in another order or mirror
        // pose) apart by far less, and a front of such twins says nothing.
        if out.last().is_none_or(|l| e.worst < l.worst * (1.0 - 1e-4)) {
            out.push(e.clone());
        }
    }
    out
}

fn place(evaluation: PlanEvaluation, front: &[PlanEvaluation]) -> ReferencePosition {
    let front_worst_at_time = front
        .iter()
        .filter(|e| e.machine_time_s <= evaluation.machine_time_s + 1e-9)
        .map(|e| e.worst)
        .min_by(f64::total_cmp);
    let front_time_at_worst = front
        .iter()
        .filter(|e| e.worst <= evaluation.worst + 1e-12)
        .map(|e| e.machine_time_s)
        .min_by(f64::total_cmp);
    ReferencePosition {
        ratio: front_worst_at_time.map(|w| evaluation.worst / w),
        front_worst_at_time,
        front_time_at_worst,
        evaluation,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn candidate_poses_follow_the_travel() {
        let k = Kinematics::builtin("table_bc").unwrap();
        let base = PlanConfig::load("patent").unwrap();
        let poses = candidate_poses(&k, &base);
        // B travels -120..120: no B = +-135 or 180.
        assert!(poses.iter().all(|p| p.b_deg.abs() <= 120.0));
        assert!(poses.iter().any(|p| p.b_deg == -90.0 && p.c_deg == -270.0));
        // The patent's poses all offer z and lateral.
        let g = genome_of(&base, &poses).expect("patent poses are candidates");
        assert_eq!(g.genes.len(), 6);
    }

    #[test]
    fn front_drops_dominated_and_equal_plans() {
        let k = Kinematics::builtin("table_bc").unwrap();
        let e = evaluate(
            &k,
            &PlanConfig::load("patent").unwrap(),
            &DesignOptions::new(0.5),
        )
        .unwrap();
        let at = |t: f64, w: f64| {
            let mut x = e.clone();
            x.machine_time_s = t;
            x.worst = w;
            x
        };
        // (30, 3) dominates (40, 3.5) and (35, 3); (50, 2) and (20, 5) stand.
        let pts = [
            at(40.0, 3.5),
            at(30.0, 3.0),
            at(50.0, 2.0),
            at(35.0, 3.0),
            at(20.0, 5.0),
        ];
        let refs: Vec<&PlanEvaluation> = pts.iter().collect();
        let f: Vec<(f64, f64)> = pareto_front(&refs)
            .iter()
            .map(|x| (x.machine_time_s, x.worst))
            .collect();
        assert_eq!(f, [(20.0, 5.0), (30.0, 3.0), (50.0, 2.0)]);
        let p = place(at(45.0, 4.0), &pareto_front(&refs));
        assert_eq!(p.front_worst_at_time, Some(3.0));
        assert_eq!(p.front_time_at_worst, Some(30.0));
    }
}
