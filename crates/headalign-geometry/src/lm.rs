//! The one Levenberg-Marquardt loop of the project (Hartley & Zisserman appendix A6.2;
//! Madsen, Nielsen, Tingleff, "Methods for non-linear least squares problems", 2004,
//! section 3.2). The rig bundle adjustment, the rig motion, the refinements of F (7
//! dof), of a 3D homography (16), of a pose (6), of a translation and of a frame, and the
//! small fits (the planar check's rotation, the steering zero, the robot stages' floor
//! normal) run it. Outside it: the patch alignment of `headalign_vision::refine`, a
//! fixed-point iteration on the template's Jacobian that is no descent method (its
//! module docs say why). Not yet: the planar route's adjustment
//! (`headalign::facing_plane::refine`, its module docs say why: its cost has several
//! minima near its starts, and under this policy some fits end in a higher one).
//!
//! # What it computes
//!
//! [`run`] minimises the cost of a [`LeastSquares`] problem from a start: at each
//! iteration the problem linearises at the accepted state (its [`Linearisation`], the back
//! end), the back end solves the damped normal equations `(H + lambda D) h = -g` (`H = J^T
//! W J`, `g = J^T W r`, `D` Marquardt's diagonal scaling [`damping_diagonal`]: invariant
//! to parameter units) and the problem moves the state by the step (its retraction). A
//! step is taken only if it lowers the cost, so the result is never worse than the start.
//! Two back ends: [`Dense`] / [`DenseDyn`] (the whole normal matrix by Cholesky, fixed
//! or dynamic size) and the point-Schur complement of the bundle adjustment
//! (`bundle/normal.rs`: the points eliminated 3x3 block by block, the reduced camera
//! system by Cholesky), which the rig motion shares (`rigmotion.rs`).
//!
//! # Damping policy
//!
//! `lambda` starts at [`INITIAL_LAMBDA`] = 1e-3 and follows Nielsen's rule (H. B. Nielsen,
//! "Damping parameter in Marquardt's method", IMM-REP 1999-05): after an accepted step
//! with gain ratio `rho` (actual over predicted decrease) `lambda *= max(1/3, 1 - (2 rho
//! - 1)^3)` (floor 1e-12), after a rejected step (or one that cannot be solved or
//! retracted) `lambda *= nu, nu *= 2` (`nu = 2` after each acceptance). The damping adds
//! `lambda` times each diagonal entry clamped to `[1e-6, 1e32]`.
//!
//! # Stopping rules, in order
//!
//! After an accepted step: relative cost decrease at most
//! [`LmOptions::function_tolerance`]; step norm at most `parameter_tolerance * (|x| +
//! parameter_tolerance)` (`|x|` the problem's [`LeastSquares::state_norm`] before the
//! step); zero cost. Before a solve: the damping limit `lambda > 1e16` (no step lowers the
//! cost: a minimum to rounding). Before a linearisation: `max_iterations` (the only rule
//! that reports not converged), or a problem that abandons ([`LeastSquares::keep_going`]).
//! A linearisation that fails stops the run where it stands.
//!
//! # Units
//!
//! Costs are half sums of squared (weighted, robustified) residuals in the residuals'
//! units (pixels for every image problem): the predicted decrease of the back ends is of
//! that half sum. Tolerances are relative, `lambda` dimensionless.
//!
//! # Pitfalls
//!
//! - The cost must be what the normal equations linearise (the same weights), or steps
//!   are refused and the run stops at the damping limit early.
//! - The order of the stopping tests and the damping constants are part of every result
//!   (the experiments' outputs are compared cell for cell).

use nalgebra::{DMatrix, DVector, SMatrix, SVector};

/// The damping at the start of every run.
pub const INITIAL_LAMBDA: f64 = 1e-3;
/// The damping beyond which no step is tried: the minimum to rounding.
pub const DAMPING_LIMIT: f64 = 1e16;
/// The smallest damping after an accepted step.
pub const LAMBDA_FLOOR: f64 = 1e-12;

/// Stopping rules of [`run`] (module docs). No default: each problem states its own.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct LmOptions {
    /// Most linearisations.
    pub max_iterations: usize,
    /// Stop when an accepted step lowers the cost by at most this fraction of it.
    pub function_tolerance: f64,
    /// Stop when an accepted step is at most `parameter_tolerance * (|x| +
    /// parameter_tolerance)` long (0 disables the rule but for a zero step).
    pub parameter_tolerance: f64,
}

/// Marquardt's scaling of the damping for a diagonal entry `d` of the normal matrix:
/// `d` clamped to `[1e-6, 1e32]` (a parameter the data do not see is still damped, and an
/// overflowing entry does not make the damped system infinite).
pub fn damping_diagonal(d: f64) -> f64 {
    d.clamp(1e-6, 1e32)
}

/// The damped normal equations at one state: the back end of [`run`].
pub trait Linearisation {
    /// A step in the problem's parameters.
    type Step;
    /// The step `h` of `(H + lambda D) h = -g` ([`damping_diagonal`]); `None` if the damped
    /// system is not positive definite.
    fn solve(&self, lambda: f64) -> Option<Self::Step>;
    /// The decrease of the local quadratic model of the half cost for `step` (solved at
    /// `lambda`): `(lambda h^T D h - g^T h) / 2`.
    fn predicted_decrease(&self, lambda: f64, step: &Self::Step) -> f64;
}

/// The cost part of a problem's evaluation of a state.
pub trait Evaluation {
    /// Half the sum of squared weighted residuals (module docs, Units).
    fn cost(&self) -> f64;
}

impl Evaluation for f64 {
    fn cost(&self) -> f64 {
        *self
    }
}

/// A least-squares problem for [`run`]: its state, how it linearises, moves and evaluates.
pub trait LeastSquares {
    /// The parameters.
    type State;
    /// The back end at a state.
    type Normal: Linearisation;
    /// What evaluating a state gives (at least the cost).
    type Eval: Evaluation;
    /// A failure that ends the run with an error.
    type Error;
    /// The normal equations at `state`; `Ok(None)` stops the run at `state`.
    fn linearise(&mut self, state: &Self::State) -> Result<Option<Self::Normal>, Self::Error>;
    /// `state` moved by `step`, and the squared norm of the step as taken; `Ok(None)`
    /// rejects the step.
    fn retract(
        &self,
        state: &Self::State,
        step: &<Self::Normal as Linearisation>::Step,
    ) -> Result<Option<(Self::State, f64)>, Self::Error>;
    /// The evaluation of `state`; `None` (or a non-finite cost) rejects it.
    fn evaluate(&self, state: &Self::State) -> Option<Self::Eval>;
    /// The norm `|x|` of the parameter tolerance.
    fn state_norm(&self, state: &Self::State) -> f64;
    /// Asked before each linearisation with the iterations done and the accepted state;
    /// false abandons the run ([`Termination::Abandoned`]).
    fn keep_going(&mut self, _iterations: usize, _state: &Self::State, _current: &Self::Eval) -> bool {
        true
    }
    /// Given the back end of an iteration that is done with it, whose storage the next
    /// [`Self::linearise`] may reuse (default: dropped).
    fn recycle(&mut self, _normal: Self::Normal) {}
}

/// Why [`run`] stopped (module docs, Stopping rules).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Termination {
    /// The relative decrease fell to the function tolerance.
    FunctionTolerance,
    /// The step fell to the parameter tolerance.
    ParameterTolerance,
    /// The cost is zero.
    ZeroCost,
    /// The damping passed [`DAMPING_LIMIT`]: no step lowers the cost.
    DampingLimit,
    /// The problem could not linearise at the accepted state.
    LinearisationFailed,
    /// `max_iterations` linearisations were done.
    MaxIterations,
    /// [`LeastSquares::keep_going`] said no.
    Abandoned,
}

impl Termination {
    /// Whether the run ended at a minimum (every rule but the iteration limit, a failed
    /// linearisation and abandonment).
    pub fn converged(self) -> bool {
        !matches!(self, Self::MaxIterations | Self::LinearisationFailed | Self::Abandoned)
    }

    /// The rule in words.
    pub fn reason(self) -> &'static str {
        match self {
            Self::FunctionTolerance => "function tolerance",
            Self::ParameterTolerance => "parameter tolerance",
            Self::ZeroCost => "zero cost",
            Self::DampingLimit => "no further decrease possible (damping limit): minimum to rounding",
            Self::LinearisationFailed => "linearisation failed",
            Self::MaxIterations => "maximum iterations reached",
            Self::Abandoned => "abandoned",
        }
    }
}

/// What [`run`] returns: the accepted state, its evaluation, the linearisations done and
/// why it stopped.
#[derive(Debug, Clone)]
pub struct Outcome<S, E> {
    /// The final (best) state.
    pub state: S,
    /// Its evaluation.
    pub value: E,
    /// Linearisations done.
    pub iterations: usize,
    /// The rule that stopped the run.
    pub termination: Termination,
}

/// Where the iteration stands: the accepted state and its evaluation, the damping and
/// Nielsen's factor `nu` by which the next rejected step raises it.
struct Iterate<S, E> {
    state: S,
    current: E,
    lambda: f64,
    nu: f64,
}

impl<S, E> Iterate<S, E> {
    /// Nielsen's damping after a rejected step: raise `lambda` by `nu`, double `nu`.
    fn reject(&mut self) {
        self.lambda *= self.nu;
        self.nu *= 2.0;
    }
}

/// Minimise `problem`'s cost from `start` (evaluated as `start_value`) by
/// Levenberg-Marquardt under the module's damping policy and stopping rules.
pub fn run<P: LeastSquares>(
    problem: &mut P,
    start: P::State,
    start_value: P::Eval,
    options: &LmOptions,
) -> Result<Outcome<P::State, P::Eval>, P::Error> {
    let mut it = Iterate { state: start, current: start_value, lambda: INITIAL_LAMBDA, nu: 2.0 };
    let mut iterations = 0;
    let mut termination = Termination::MaxIterations;
    while iterations < options.max_iterations {
        if !problem.keep_going(iterations, &it.state, &it.current) {
            termination = Termination::Abandoned;
            break;
        }
        iterations += 1;
        let Some(normal) = problem.linearise(&it.state)? else {
            termination = Termination::LinearisationFailed;
            break;
        };
        let stop = step(problem, options, &normal, &mut it)?;
        problem.recycle(normal);
        if let Some(stop) = stop {
            termination = stop;
            break;
        }
    }
    let Iterate { state, current, .. } = it;
    Ok(Outcome { state, value: current, iterations, termination })
}

/// One linearisation's worth of Levenberg-Marquardt: solve the damped system, try the
/// step, and on failure (no solution, no retraction, no decrease) raise the damping and
/// solve again, until a step is accepted ([`accept`]) or the damping passes
/// [`DAMPING_LIMIT`]. Returns the rule that stops the run, `None` to linearise again.
fn step<P: LeastSquares>(
    problem: &P,
    options: &LmOptions,
    normal: &P::Normal,
    it: &mut Iterate<P::State, P::Eval>,
) -> Result<Option<Termination>, P::Error> {
    loop {
        if it.lambda > DAMPING_LIMIT {
            return Ok(Some(Termination::DampingLimit));
        }
        let Some(h) = normal.solve(it.lambda) else {
            it.reject();
            continue;
        };
        let predicted = normal.predicted_decrease(it.lambda, &h);
        let Some((cand, step_sq)) = problem.retract(&it.state, &h)? else {
            it.reject();
            continue;
        };
        match problem.evaluate(&cand) {
            Some(e) if e.cost() < it.current.cost() => {
                let x_norm = problem.state_norm(&it.state);
                return Ok(accept(options, it, cand, e, predicted, step_sq, x_norm));
            }
            _ => it.reject(),
        }
    }
}

/// Take the step to `cand` (evaluation `e`, of lower cost): update the damping by
/// Nielsen's rule from the gain ratio of the actual to the `predicted` decrease, then test
/// the stopping rules in order (function tolerance, parameter tolerance on the step's norm
/// `sqrt(step_sq)` against `x_norm`, the norm of the state before the step, zero cost).
fn accept<S, E: Evaluation>(
    options: &LmOptions,
    it: &mut Iterate<S, E>,
    cand: S,
    e: E,
    predicted: f64,
    step_sq: f64,
    x_norm: f64,
) -> Option<Termination> {
    let old_cost = it.current.cost();
    let decrease = old_cost - e.cost();
    it.state = cand;
    it.current = e;
    // Lower the damping by up to 3x where the quadratic model predicted the decrease well
    // (gain ratio near 1), raise it where it did not (ratio near 0).
    let gain = decrease / predicted;
    let factor = if gain.is_finite() && predicted > 0.0 {
        (1.0 - (2.0 * gain - 1.0).powi(3)).max(1.0 / 3.0)
    } else {
        1.0
    };
    it.lambda = (it.lambda * factor).max(LAMBDA_FLOOR);
    it.nu = 2.0;
    if decrease <= options.function_tolerance * old_cost {
        return Some(Termination::FunctionTolerance);
    }
    if step_sq.sqrt() <= options.parameter_tolerance * (x_norm + options.parameter_tolerance) {
        return Some(Termination::ParameterTolerance);
    }
    if it.current.cost() == 0.0 {
        return Some(Termination::ZeroCost);
    }
    None
}

/// Dense normal equations of `N` parameters, `H = J^T W J` and `g = J^T W r`: the dense
/// back end of fixed size.
#[derive(Debug, Clone, PartialEq)]
pub struct Dense<const N: usize> {
    /// `J^T W J`.
    pub jtj: SMatrix<f64, N, N>,
    /// `J^T W r`.
    pub jtr: SVector<f64, N>,
}

impl<const N: usize> Linearisation for Dense<N> {
    type Step = SVector<f64, N>;

    fn solve(&self, lambda: f64) -> Option<Self::Step> {
        let mut a = self.jtj;
        for i in 0..N {
            a[(i, i)] += lambda * damping_diagonal(self.jtj[(i, i)]);
        }
        a.cholesky().map(|c| c.solve(&(-self.jtr)))
    }

    fn predicted_decrease(&self, lambda: f64, step: &Self::Step) -> f64 {
        let h_d_h: f64 = (0..N).map(|i| damping_diagonal(self.jtj[(i, i)]) * step[i] * step[i]).sum();
        0.5 * (lambda * h_d_h - self.jtr.dot(step))
    }
}

/// Dense normal equations of a size known at run time: the dense back end of dynamic size
/// (as [`Dense`]).
#[derive(Debug, Clone, PartialEq)]
pub struct DenseDyn {
    /// `J^T W J`, square.
    pub jtj: DMatrix<f64>,
    /// `J^T W r`, as long as `jtj`.
    pub jtr: DVector<f64>,
}

impl Linearisation for DenseDyn {
    type Step = DVector<f64>;

    fn solve(&self, lambda: f64) -> Option<Self::Step> {
        let mut a = self.jtj.clone();
        for i in 0..a.nrows() {
            a[(i, i)] += lambda * damping_diagonal(self.jtj[(i, i)]);
        }
        a.cholesky().map(|c| c.solve(&(-&self.jtr)))
    }

    fn predicted_decrease(&self, lambda: f64, step: &Self::Step) -> f64 {
        let h_d_h: f64 =
            (0..step.len()).map(|i| damping_diagonal(self.jtj[(i, i)]) * step[i] * step[i]).sum();
        0.5 * (lambda * h_d_h - self.jtr.dot(step))
    }
}

/// A dense problem of `N` parameters from closures (the small refinements): the normal
/// equations `(J^T W J, J^T W r)` at a state (`None`: stop there), a retraction `state (+)
/// delta` (`None`: reject the step) and the cost `sum w r^2` they linearise (not halved:
/// [`minimise`] halves it for [`run`]).
struct Closures<S, const N: usize, NE, R, C> {
    normal: NE,
    retract: R,
    cost: C,
    state: std::marker::PhantomData<fn(&S)>,
}

impl<const N: usize, S, NE, R, C> LeastSquares for Closures<S, N, NE, R, C>
where
    NE: Fn(&S) -> Option<(SMatrix<f64, N, N>, SVector<f64, N>)>,
    R: Fn(&S, &SVector<f64, N>) -> Option<S>,
    C: Fn(&S) -> f64,
{
    type State = S;
    type Normal = Dense<N>;
    type Eval = f64;
    type Error = std::convert::Infallible;

    fn linearise(&mut self, state: &S) -> Result<Option<Dense<N>>, Self::Error> {
        Ok((self.normal)(state).map(|(jtj, jtr)| Dense { jtj, jtr }))
    }

    fn retract(&self, state: &S, step: &SVector<f64, N>) -> Result<Option<(S, f64)>, Self::Error> {
        Ok((self.retract)(state, step).map(|s| (s, step.norm_squared())))
    }

    fn evaluate(&self, state: &S) -> Option<f64> {
        let c = 0.5 * (self.cost)(state);
        c.is_finite().then_some(c)
    }

    fn state_norm(&self, _state: &S) -> f64 {
        0.0
    }
}

/// The stopping rules of [`minimise`]: a relative decrease of 1e-14 (the cost to rounding;
/// well below any printed digit of a parameter), no parameter tolerance.
pub const MINIMISE_FUNCTION_TOLERANCE: f64 = 1e-14;

/// Minimise `cost` (a sum of squared weighted residuals, not halved) of a dense problem of
/// `N` parameters from `start` (whose cost is `start_cost`) by [`run`], with the normal
/// equations `(J^T W J, J^T W r)` at a state and a retraction `state (+) delta`. Stops by
/// [`MINIMISE_FUNCTION_TOLERANCE`], the damping limit or after `max_iterations`. Returns
/// the final state and its cost; never a state worse than the start.
pub fn minimise<const N: usize, S>(
    start: S,
    start_cost: f64,
    max_iterations: usize,
    normal_equations: impl Fn(&S) -> Option<(SMatrix<f64, N, N>, SVector<f64, N>)>,
    retract: impl Fn(&S, &SVector<f64, N>) -> Option<S>,
    cost: impl Fn(&S) -> f64,
) -> (S, f64) {
    let options = LmOptions {
        max_iterations,
        function_tolerance: MINIMISE_FUNCTION_TOLERANCE,
        parameter_tolerance: 0.0,
    };
    minimise_with(start, start_cost, &options, normal_equations, retract, cost)
}

/// [`minimise`] under the stopping rules `options` (the parameter tolerance against `|x| =
/// 0`: a step at most `parameter_tolerance^2` long). A function tolerance of 0 runs to
/// rounding: until no step lowers the cost (the damping limit), what a fit that is
/// differentiated numerically needs.
pub fn minimise_with<const N: usize, S>(
    start: S,
    start_cost: f64,
    options: &LmOptions,
    normal_equations: impl Fn(&S) -> Option<(SMatrix<f64, N, N>, SVector<f64, N>)>,
    retract: impl Fn(&S, &SVector<f64, N>) -> Option<S>,
    cost: impl Fn(&S) -> f64,
) -> (S, f64) {
    let mut problem =
        Closures { normal: normal_equations, retract, cost, state: std::marker::PhantomData::<fn(&S)> };
    match run(&mut problem, start, 0.5 * start_cost, options) {
        Ok(out) => (out.state, 2.0 * out.value),
        Err(never) => match never {},
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::{Matrix2, Vector2};

    /// Rosenbrock's valley as least squares, r = (10 (y - x^2), 1 - x): the minimum (1, 1)
    /// to 1e-8 from (-1.2, 1) (Gauss-Newton is exact at a zero-residual minimum).
    #[test]
    fn minimises_rosenbrock() {
        let res = |p: &Vector2<f64>| Vector2::new(10.0 * (p.y - p.x * p.x), 1.0 - p.x);
        let cost = |p: &Vector2<f64>| res(p).norm_squared();
        let normal = |p: &Vector2<f64>| {
            let j = Matrix2::new(-20.0 * p.x, 10.0, -1.0, 0.0);
            Some((j.transpose() * j, j.transpose() * res(p)))
        };
        let start = Vector2::new(-1.2, 1.0);
        let (p, c) = minimise(start, cost(&start), 200, normal, |p, d| Some(p + d), cost);
        assert!((p - Vector2::new(1.0, 1.0)).norm() < 1e-8 && c < 1e-16, "{p} {c}");
    }

    /// A noise-free curve fit through the dynamic dense back end: `y = a exp(b x) + c` at
    /// 20 samples from a start 30-50 % off; the truth is the isolated zero-residual
    /// minimum, so the run ends in Gauss-Newton at rounding level: parameters to 1e-12
    /// (their size is 1, the Jacobian well conditioned on x in [0, 2]), by zero cost or
    /// the function tolerance.
    struct Curve {
        xs: Vec<f64>,
        ys: Vec<f64>,
    }

    impl Curve {
        fn residuals(&self, p: &DVector<f64>) -> Vec<f64> {
            self.xs.iter().zip(&self.ys).map(|(x, y)| p[0] * (p[1] * x).exp() + p[2] - y).collect()
        }
    }

    impl LeastSquares for Curve {
        type State = DVector<f64>;
        type Normal = DenseDyn;
        type Eval = f64;
        type Error = ();

        fn linearise(&mut self, p: &DVector<f64>) -> Result<Option<DenseDyn>, ()> {
            let r = self.residuals(p);
            let mut jtj = DMatrix::zeros(3, 3);
            let mut jtr = DVector::zeros(3);
            for (x, ri) in self.xs.iter().zip(r) {
                let e = (p[1] * x).exp();
                let j = DVector::from_vec(vec![e, p[0] * x * e, 1.0]);
                jtj += &j * j.transpose();
                jtr += j * ri;
            }
            Ok(Some(DenseDyn { jtj, jtr }))
        }

        fn retract(&self, p: &DVector<f64>, d: &DVector<f64>) -> Result<Option<(DVector<f64>, f64)>, ()> {
            Ok(Some((p + d, d.norm_squared())))
        }

        fn evaluate(&self, p: &DVector<f64>) -> Option<f64> {
            Some(0.5 * self.residuals(p).iter().map(|r| r * r).sum::<f64>())
        }

        fn state_norm(&self, p: &DVector<f64>) -> f64 {
            p.norm()
        }
    }

    #[test]
    fn dynamic_dense_fit_reaches_the_truth() {
        let truth = DVector::from_vec(vec![1.5, -0.7, 0.3]);
        let xs: Vec<f64> = (0..20).map(|i| 0.1 * i as f64).collect();
        let ys = xs.iter().map(|x| truth[0] * (truth[1] * x).exp() + truth[2]).collect();
        let mut curve = Curve { xs, ys };
        let start = DVector::from_vec(vec![1.0, -1.0, 0.4]);
        let value = curve.evaluate(&start).unwrap();
        let options = LmOptions { max_iterations: 100, function_tolerance: 1e-14, parameter_tolerance: 0.0 };
        let out = run(&mut curve, start, value, &options).unwrap();
        assert!(out.termination.converged(), "{:?}", out.termination);
        assert!((&out.state - &truth).norm() < 1e-12, "{} after {} iterations", out.state, out.iterations);
        // The iteration limit stops a run early and says so.
        let start = DVector::from_vec(vec![1.0, -1.0, 0.4]);
        let capped = LmOptions { max_iterations: 1, ..options };
        let out = run(&mut curve, start, value, &capped).unwrap();
        assert_eq!((out.iterations, out.termination), (1, Termination::MaxIterations));
        assert!(out.value < value);
    }
}
