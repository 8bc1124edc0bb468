//! Model families that compete for one displacement channel, judged the same way on the
//! same points: the pole-basis grey box of [`crate::model`] and the textbook
//! baselines a thermal engineer would try first, persistence (the last training value held),
//! multiple linear regression on every temperature, regression on a few key temperatures
//! chosen by forward selection, and an ARX model run in simulation (free-run, multi-step)
//! mode; and the inverse-MSE combination of all but persistence. Every family is scored by
//! rolling-origin (forward-chaining) cross-validation on the training span only: at each
//! origin it is fitted on what came before (its own choices, the key sensors or the ARX
//! orders, made again inside) and predicts freely to the end of the span, with no reading
//! after the origin. The chosen family has the lowest CV error; persistence and regression
//! are among the candidates, so the choice never loses to them in CV. Its band is the CV
//! errors' quantiles by horizon ([`Bands`]), judged on each fold against the others.
//!
//! Pure: plain data in and out, no I/O.

mod bands;
mod channel;
mod choice;
mod compete;
mod cv;
mod fit;
mod fitted;
mod grid;

pub use bands::{BAND_EDGES_H, Bands, FreeRunScore, coverage, score_free_run};
pub use channel::{ChannelChoice, Served, choose, describe_served, fit_scored};
pub use choice::{
    Choice, MIN_BEYOND, RANGE_SLACK, RegimeChoice, excursion, excursion_by_input,
    independent_folds, input_ranges,
};
pub use compete::{FamilyScore, compete};
pub use cv::{
    CvError, N_FOLDS, RELAX_H, folds, origin_residual, relax_weight, rms, tested_horizon,
};
pub(crate) use fit::forward_select;
pub use fit::{MAX_KEY, fit_family, grey_box, grey_box_config, key_inputs};
pub use fitted::{Family, Fitted, simulate, simulate_with};
pub use grid::{Grid, default_step_ns, grid};

#[cfg(test)]
mod tests;
