//! Evaluation (DESIGN stage 9): image metrics of the held-out relighting, errors of an estimated
//! calibration against the truth, and the process's resource use.

pub mod calibration_error;
pub mod metrics;
pub mod resources;
