//! Evaluation (DESIGN stage 9): the held-out relighting and its image metrics, back-scatter, the
//! runtime-versus-error sweep of the quality knobs, errors of an estimated calibration against the
//! truth, and the process's resource use.

pub mod backscatter;
pub mod calibration_error;
pub mod holdout;
pub mod metrics;
pub mod separation_race;
pub mod skin_types;
pub mod stripe_sweep;
