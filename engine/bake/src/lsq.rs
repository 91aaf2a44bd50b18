//! Least-squares problems for Levenberg–Marquardt with a central-difference Jacobian: a model
//! gives its residuals at any parameter vector and a step size, [`Numeric`] does the rest.

use levenberg_marquardt::LeastSquaresProblem;
use nalgebra::{DMatrix, DVector, Dyn, Owned};

/// A residual function of a parameter vector.
pub trait ResidualModel {
    /// Residuals at `p`.
    fn residuals_at(&self, p: &DVector<f64>) -> DVector<f64>;
    /// Central-difference step for a parameter whose value is `v`.
    fn step(&self, v: f64) -> f64;
}

/// A [`ResidualModel`] at a parameter vector, as a `levenberg_marquardt` problem.
pub struct Numeric<M> {
    /// The model.
    pub model: M,
    /// Current parameters.
    pub p: DVector<f64>,
}

impl<M: ResidualModel> LeastSquaresProblem<f64, Dyn, Dyn> for Numeric<M> {
    type ResidualStorage = Owned<f64, Dyn>;
    type JacobianStorage = Owned<f64, Dyn, Dyn>;
    type ParameterStorage = Owned<f64, Dyn>;

    fn set_params(&mut self, x: &DVector<f64>) {
        self.p.copy_from(x);
    }

    fn params(&self) -> DVector<f64> {
        self.p.clone()
    }

    fn residuals(&self) -> Option<DVector<f64>> {
        Some(self.model.residuals_at(&self.p))
    }

    fn jacobian(&self) -> Option<DMatrix<f64>> {
        let base = &self.p;
        let mut j: Option<DMatrix<f64>> = None;
        for k in 0..base.len() {
            let h = self.model.step(base[k]);
            let mut up = base.clone();
            up[k] += h;
            let mut down = base.clone();
            down[k] -= h;
            let col = (self.model.residuals_at(&up) - self.model.residuals_at(&down)) / (2.0 * h);
            j.get_or_insert_with(|| DMatrix::zeros(col.len(), base.len()))
                .set_column(k, &col);
        }
        j
    }
}
