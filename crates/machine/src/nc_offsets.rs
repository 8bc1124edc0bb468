//! What one machine's compensation sets hold and the form its NC takes them in: the location
//! errors its cycle identifies (report order) and each NC offset as a fixed linear combination
//! of them, derived from the machine's kinematics, so that every family of
//! `config/machines/` gets its own without code of its own.
//!
//! The NC's kinematic model must put each axis line where the actual line is. An offset is the
//! nominal-to-actual move of one line at the zero pose:
//!
//! - `{axis}_pivot_{x|y|z}_um`: the line's move square to its own direction, in machine
//!   coordinates for a table axis and head-frame coordinates for a head axis (the pivot vector
//!   of the NC's head model). A line measured from its parent (`relative_to_parent`) moves with
//!   it, so its offset adds the parent's move square to its own direction: on `table_bc`,
//!   `C_pivot_x_um = EX0B + EX0C`. Components that no identified error moves are left out (a
//!   line has no position along itself).
//! - `{axis}_tilt_{a|b|c}_urad`: an identified orientation error of the line, the rotation
//!   about the axis its name gives (an inclined axis' own frame for its own errors), right-hand
//!   rule; `{axis}_zero_urad` an identified zero-angle error.
//! - `{axis}_dir_{x|y|z}_urad`: the same tilts as the change of the line's unit direction
//!   vector, per machine component (first order; the form of NCs whose kinematics take an
//!   axis direction vector): on `table_bc` `C_dir_x_urad = EB0C`, `C_dir_y_urad = -EA0C`.
//!
//! Held (not identified) errors are not in a set, so they move no offset. On `table_bc` this
//! is the convention the project has always served: `B_pivot_x_um = EX0B`,
//! `B_pivot_z_um = EZ0B`, `C_pivot_x_um = EX0B + EX0C`, `C_pivot_y_um = EY0C`,
//! `C_tilt_a_urad = EA0C`, `C_tilt_b_urad = EB0C`.

use std::collections::BTreeMap;

use driftwatch_core::error_name::ErrorName;
use driftwatch_core::geometry::Vec3;
use driftwatch_core::kinematics::{ErrorId, Kinematics};

/// One NC offset: its name, unit and the identified errors it sums, with their weights.
#[derive(Debug, Clone, PartialEq)]
pub struct Offset {
    pub name: String,
    pub unit: &'static str,
    pub terms: Vec<(ErrorName, f64)>,
}

/// The identified errors of one machine and the NC offsets they make.
#[derive(Debug, Clone, PartialEq)]
pub struct NcLayout {
    /// The machine's name (`table_bc`, ...), for messages.
    pub machine: String,
    /// The identified errors, in report order: exactly what a set holds.
    pub errors: Vec<ErrorName>,
    pub offsets: Vec<Offset>,
}

/// Weights below this are rounding of unit vectors, not a dependence.
const NEGLIGIBLE: f64 = 1e-12;

impl NcLayout {
    pub fn of(k: &Kinematics) -> Self {
        let errors: Vec<ErrorName> = k.identify.iter().map(|id| name_of(k, *id)).collect();
        let mut offsets = Vec::new();
        for (i, ax) in k.rotary.iter().enumerate() {
            // The line's move per unit of each identified position error (its own and, when
            // measured from its parent, the parent's move square to this line).
            let moves: Vec<(ErrorName, Vec3)> = line_moves(k, i)
                .into_iter()
                .filter(|(id, _)| k.identify.contains(id))
                .map(|(id, v)| (name_of(k, id), v))
                .collect();
            by_component(&mut offsets, &format!("{}_pivot", ax.name), "um", &moves);
            // The direction vector's first-order change per identified tilt: o x u0.
            let tilts: Vec<(ErrorName, Vec3)> = (2..4)
                .map(|slot| ErrorId { axis: i, slot })
                .filter(|id| k.identify.contains(id))
                .map(|id| {
                    (
                        name_of(k, id),
                        ax.orientation_axes[id.slot - 2].cross(&ax.u0),
                    )
                })
                .collect();
            by_component(&mut offsets, &format!("{}_dir", ax.name), "urad", &tilts);
            for slot in 2..5 {
                let id = ErrorId { axis: i, slot };
                if !k.identify.contains(&id) {
                    continue;
                }
                let n = name_of(k, id);
                let name = if slot == 4 {
                    format!("{}_zero_urad", ax.name)
                } else {
                    format!(
                        "{}_tilt_{}_urad",
                        ax.name,
                        n.component().to_ascii_lowercase()
                    )
                };
                offsets.push(Offset {
                    name,
                    unit: "urad",
                    terms: vec![(n, 1.0)],
                });
            }
        }
        NcLayout {
            machine: k.name.clone(),
            errors,
            offsets,
        }
    }

    /// The NC offsets of a set's errors. An offset whose inputs are missing or not finite is
    /// left out rather than guessed.
    pub fn offsets(&self, errors: &BTreeMap<ErrorName, f64>) -> BTreeMap<String, f64> {
        self.offsets
            .iter()
            .filter_map(|o| {
                let mut sum = 0.0;
                for (n, w) in &o.terms {
                    let v = errors.get(n).copied().filter(|v| v.is_finite())?;
                    sum += w * v;
                }
                Some((o.name.clone(), sum))
            })
            .collect()
    }

    /// The identified errors as a list for messages ("EX0B, EZ0B, ...").
    pub fn list(&self) -> String {
        self.errors
            .iter()
            .map(|n| n.as_str())
            .collect::<Vec<_>>()
            .join(", ")
    }

    pub fn holds(&self, name: &str) -> bool {
        self.errors.iter().any(|n| *n == name)
    }
}

/// One offset `{prefix}_{x|y|z}_{unit}` per machine component that any of the errors moves,
/// each error weighted by its vector's component.
fn by_component(
    offsets: &mut Vec<Offset>,
    prefix: &str,
    unit: &'static str,
    moves: &[(ErrorName, Vec3)],
) {
    for (c, letter) in ["x", "y", "z"].iter().enumerate() {
        let terms: Vec<(ErrorName, f64)> = moves
            .iter()
            .filter(|(_, v)| v[c].abs() > NEGLIGIBLE)
            .map(|(n, v)| (*n, v[c]))
            .collect();
        if !terms.is_empty() {
            offsets.push(Offset {
                name: format!("{prefix}_{letter}_{unit}"),
                unit,
                terms,
            });
        }
    }
}

fn name_of(k: &Kinematics, id: ErrorId) -> ErrorName {
    k.rotary[id.axis].error_names[id.slot]
}

/// How axis `i`'s line moves per unit (mm per mm) of each position error it depends on, as
/// `Kinematics::lines` moves it.
fn line_moves(k: &Kinematics, i: usize) -> Vec<(ErrorId, Vec3)> {
    let ax = &k.rotary[i];
    let mut out: Vec<(ErrorId, Vec3)> = (0..2)
        .map(|slot| (ErrorId { axis: i, slot }, ax.position_dirs[slot]))
        .collect();
    if ax.relative_to_parent
        && let Some(p) = (0..i).rev().find(|p| k.rotary[*p].side == ax.side)
    {
        for (id, v) in line_moves(k, p) {
            out.push((id, v - ax.u0 * v.dot(&ax.u0)));
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    fn layout(name: &str) -> NcLayout {
        NcLayout::of(&Kinematics::builtin(name).unwrap())
    }

    fn names(l: &NcLayout) -> Vec<(String, Vec<(String, f64)>)> {
        l.offsets
            .iter()
            .map(|o| {
                (
                    o.name.clone(),
                    o.terms
                        .iter()
                        .map(|(n, w)| (n.to_string(), (w * 1e6).round() / 1e6))
                        .collect(),
                )
            })
            .collect()
    }

    fn t(name: &str, terms: &[(&str, f64)]) -> (String, Vec<(String, f64)>) {
        (
            name.to_string(),
            terms.iter().map(|(n, w)| (n.to_string(), *w)).collect(),
        )
    }

    #[test]
    fn table_bc_keeps_its_convention() {
        let l = layout("table_bc");
        assert_eq!(l.list(), "EX0B, EZ0B, EY0C, EX0C, EA0C, EB0C");
        assert_eq!(
            names(&l),
            vec![
                t("B_pivot_x_um", &[("EX0B", 1.0)]),
                t("B_pivot_z_um", &[("EZ0B", 1.0)]),
                t("C_pivot_x_um", &[("EX0C", 1.0), ("EX0B", 1.0)]),
                t("C_pivot_y_um", &[("EY0C", 1.0)]),
                t("C_dir_x_urad", &[("EB0C", 1.0)]),
                t("C_dir_y_urad", &[("EA0C", -1.0)]),
                t("C_tilt_a_urad", &[("EA0C", 1.0)]),
                t("C_tilt_b_urad", &[("EB0C", 1.0)]),
            ]
        );
    }

    /// Each family's offsets: the D pivot in machine coordinates (its Z' error moves the line
    /// along (0, -1, 1)/sqrt2), the C line measured from D or A inheriting their move square
    /// to Z, the head pivots in the head frame.
    #[test]
    fn every_family_gets_the_offsets_of_its_own_lines() {
        let h = (std::f64::consts::FRAC_1_SQRT_2 * 1e6).round() / 1e6;
        assert_eq!(
            names(&layout("table_d45_c")),
            vec![
                t("D_pivot_x_um", &[("EX0D", 1.0)]),
                t("D_pivot_y_um", &[("EZ0D", -h)]),
                t("D_pivot_z_um", &[("EZ0D", h)]),
                t("C_pivot_x_um", &[("EX0C", 1.0), ("EX0D", 1.0)]),
                t("C_pivot_y_um", &[("EY0C", 1.0), ("EZ0D", -h)]),
                t("C_dir_x_urad", &[("EB0C", 1.0)]),
                t("C_dir_y_urad", &[("EA0C", -1.0)]),
                t("C_tilt_a_urad", &[("EA0C", 1.0)]),
                t("C_tilt_b_urad", &[("EB0C", 1.0)]),
            ]
        );
        assert_eq!(
            names(&layout("trunnion_ac")),
            vec![
                t("A_pivot_y_um", &[("EY0A", 1.0)]),
                t("A_pivot_z_um", &[("EZ0A", 1.0)]),
                t("C_pivot_x_um", &[("EX0C", 1.0)]),
                t("C_pivot_y_um", &[("EY0C", 1.0), ("EY0A", 1.0)]),
                t("C_dir_x_urad", &[("EB0C", 1.0)]),
                t("C_dir_y_urad", &[("EA0C", -1.0)]),
                t("C_tilt_a_urad", &[("EA0C", 1.0)]),
                t("C_tilt_b_urad", &[("EB0C", 1.0)]),
            ]
        );
        // The head's pivot is not the table's parent: C stands on its own.
        let hb = names(&layout("head_b_table_c"));
        assert!(hb.contains(&t("B_pivot_x_um", &[("EX0B", 1.0)])));
        assert!(hb.contains(&t("C_pivot_x_um", &[("EX0C", 1.0)])));
        assert_eq!(names(&layout("head_d45_table_c")).len(), 9);
    }

    #[test]
    fn a_missing_input_leaves_its_offset_out() {
        let l = layout("table_bc");
        let mut e: BTreeMap<ErrorName, f64> = l.errors.iter().map(|n| (*n, 2.0)).collect();
        e.insert(ErrorName::from_static("EX0B"), f64::NAN);
        let o = l.offsets(&e);
        assert!(!o.contains_key("B_pivot_x_um") && !o.contains_key("C_pivot_x_um"));
        assert_eq!(o["C_pivot_y_um"], 2.0);
    }
}
