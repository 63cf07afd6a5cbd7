//! Levenberg-Marquardt for small dense non-linear least squares (a few hundred parameters, a few
//! thousand residuals), with a central-difference Jacobian computed in parallel.
//!
//! Marquardt's scaling is used: the damped normal equations are
//! `(J^T J + lambda diag(J^T J)) delta = -J^T r`, so every parameter is damped in its own units.

use nalgebra::{DMatrix, DVector};
use rayon::prelude::*;

/// Why the optimisation could not run.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
#[non_exhaustive]
pub enum LmError {
    /// The residuals at the starting point are not finite.
    #[error("the residuals at the starting point are not finite (bad initial estimate)")]
    NonFiniteStart,
    /// Fewer residuals than free parameters.
    #[error("{residuals} residuals cannot determine {parameters} free parameters")]
    Underdetermined { residuals: usize, parameters: usize },
}

/// Stopping rules.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct LmOptions {
    pub max_iterations: usize,
    /// Stop when the relative decrease of the cost in an accepted step is below this.
    pub cost_tolerance: f64,
}

impl Default for LmOptions {
    fn default() -> Self {
        Self {
            max_iterations: 100,
            cost_tolerance: 1e-10,
        }
    }
}

/// Outcome of a minimisation.
#[derive(Debug, Clone, PartialEq)]
pub struct LmOutcome {
    pub parameters: DVector<f64>,
    /// Sum of squared residuals at the start and at the end.
    pub initial_cost: f64,
    pub final_cost: f64,
    pub iterations: usize,
}

/// Minimises `sum(residuals(x)^2)` from `x0`. Parameters with `free[i] == false` are held fixed.
/// `residuals` must always return the same number of values; non-finite values make a step fail.
pub fn minimise<F>(
    residuals: F,
    x0: DVector<f64>,
    free: &[bool],
    options: &LmOptions,
) -> Result<LmOutcome, LmError>
where
    F: Fn(&DVector<f64>) -> Vec<f64> + Sync,
{
    let free_index: Vec<usize> = (0..x0.len()).filter(|&i| free[i]).collect();
    let r0 = residuals(&x0);
    if r0.iter().any(|v| !v.is_finite()) {
        return Err(LmError::NonFiniteStart);
    }
    if r0.len() < free_index.len() {
        return Err(LmError::Underdetermined {
            residuals: r0.len(),
            parameters: free_index.len(),
        });
    }
    let cost = |r: &[f64]| r.iter().map(|v| v * v).sum::<f64>();
    let mut x = x0;
    let mut r = DVector::from_vec(r0);
    let initial_cost = cost(r.as_slice());
    let mut current = initial_cost;
    let mut lambda = 1e-3;
    let mut iterations = 0;
    while iterations < options.max_iterations {
        iterations += 1;
        let jac = jacobian(&residuals, &x, &free_index, r.len());
        let jtj = jac.transpose() * &jac;
        let jtr = jac.transpose() * &r;
        let mut accepted = false;
        while lambda < 1e12 {
            let mut a = jtj.clone();
            for i in 0..a.nrows() {
                a[(i, i)] += lambda * jtj[(i, i)].max(1e-12);
            }
            let Some(chol) = a.cholesky() else {
                lambda *= 10.0;
                continue;
            };
            let delta = chol.solve(&(-&jtr));
            let mut candidate = x.clone();
            for (k, &i) in free_index.iter().enumerate() {
                candidate[i] += delta[k];
            }
            let rc = residuals(&candidate);
            let c = cost(&rc);
            if c.is_finite() && c < current {
                let relative = (current - c) / current.max(1e-300);
                x = candidate;
                r = DVector::from_vec(rc);
                current = c;
                lambda = (lambda * 0.3).max(1e-12);
                accepted = true;
                if relative < options.cost_tolerance {
                    return Ok(LmOutcome {
                        parameters: x,
                        initial_cost,
                        final_cost: current,
                        iterations,
                    });
                }
                break;
            }
            lambda *= 10.0;
        }
        if !accepted {
            break;
        }
    }
    Ok(LmOutcome {
        parameters: x,
        initial_cost,
        final_cost: current,
        iterations,
    })
}

/// Standard errors of the free parameters at `x` (in `free` order, `None` for fixed ones), from
/// the Gauss-Newton covariance `sigma^2 (J^T J)^-1` with `sigma` the residuals' standard deviation
/// (never taken below `sigma_floor`, so exact data does not hide an unobservable parameter).
/// `None` when `J^T J` is singular: some combination of parameters is not observed at all.
pub fn standard_errors<F>(
    residuals: F,
    x: &DVector<f64>,
    free: &[bool],
    sigma_floor: f64,
) -> Option<Vec<Option<f64>>>
where
    F: Fn(&DVector<f64>) -> Vec<f64> + Sync,
{
    let free_index: Vec<usize> = (0..x.len()).filter(|&i| free[i]).collect();
    let r = residuals(x);
    let dof = r.len().checked_sub(free_index.len()).filter(|&d| d > 0)?;
    let sigma2 = (r.iter().map(|v| v * v).sum::<f64>() / dof as f64).max(sigma_floor.powi(2));
    let jac = jacobian(&residuals, x, &free_index, r.len());
    let covariance = (jac.transpose() * &jac).cholesky()?.inverse();
    let mut errors = vec![None; x.len()];
    for (k, &i) in free_index.iter().enumerate() {
        let variance = sigma2 * covariance[(k, k)];
        errors[i] = Some(variance.max(0.0).sqrt()).filter(|e| e.is_finite());
    }
    Some(errors)
}

/// Central-difference Jacobian of the free parameters (columns in `free_index` order).
fn jacobian<F>(residuals: &F, x: &DVector<f64>, free_index: &[usize], rows: usize) -> DMatrix<f64>
where
    F: Fn(&DVector<f64>) -> Vec<f64> + Sync,
{
    let columns: Vec<Vec<f64>> = free_index
        .par_iter()
        .map(|&i| {
            let h = 1e-6 * (x[i].abs() + 1.0);
            let mut plus = x.clone();
            plus[i] += h;
            let mut minus = x.clone();
            minus[i] -= h;
            let (rp, rm) = (residuals(&plus), residuals(&minus));
            rp.iter()
                .zip(&rm)
                .map(|(a, b)| {
                    let d = (a - b) / (2.0 * h);
                    if d.is_finite() { d } else { 0.0 }
                })
                .collect()
        })
        .collect();
    DMatrix::from_fn(rows, free_index.len(), |r, c| columns[c][r])
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn fits_an_exponential_and_respects_fixed_parameters() {
        // y = a exp(b t) + c with c held at its true value.
        let (a, b, c) = (2.5, -0.7, 0.3);
        let ts: Vec<f64> = (0..30).map(|i| i as f64 * 0.2).collect();
        let ys: Vec<f64> = ts.iter().map(|t| a * (b * t).exp() + c).collect();
        let f = |x: &DVector<f64>| -> Vec<f64> {
            ts.iter()
                .zip(&ys)
                .map(|(t, y)| x[0] * (x[1] * t).exp() + x[2] - y)
                .collect()
        };
        let out = minimise(
            f,
            DVector::from_vec(vec![1.0, -0.1, c]),
            &[true, true, false],
            &LmOptions::default(),
        )
        .unwrap();
        assert!((out.parameters[0] - a).abs() < 1e-7, "{out:?}");
        assert!((out.parameters[1] - b).abs() < 1e-7);
        assert_eq!(out.parameters[2], c);
        assert!(out.final_cost < 1e-14 && out.initial_cost > 1.0);
    }

    #[test]
    fn refuses_underdetermined_and_non_finite_problems() {
        let f = |x: &DVector<f64>| vec![x[0] + x[1]];
        assert!(matches!(
            minimise(f, DVector::zeros(2), &[true, true], &LmOptions::default()),
            Err(LmError::Underdetermined { .. })
        ));
        let g = |x: &DVector<f64>| vec![(x[0] - 1.0).ln(), x[0]];
        assert_eq!(
            minimise(g, DVector::zeros(1), &[true], &LmOptions::default()),
            Err(LmError::NonFiniteStart)
        );
    }
}
