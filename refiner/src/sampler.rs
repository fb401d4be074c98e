//! Flow-matching sampling: the sigma schedule, Euler, and UniPC (order 2, `bh2`, x0-predicting).
//!
//! The model sees `x_σ = (1 − σ)·x0 + σ·noise` and predicts the velocity `v = noise − x0`, so
//! `x0 = x − σ·v`. A sampler walks a [`Schedule`] of shifted sigmas from about 1 down to 0.
//!
//! Each sampler uses the schedule the reference pipeline (diffusers' WanVACEPipeline) gives it, so
//! that our latents match its step for step:
//! - UniPC reproduces `UniPCMultistepScheduler` as Wan ships it (`use_flow_sigmas`,
//!   `prediction_type = "flow_prediction"`, `solver_order = 2`, `bh2`, `lower_order_final`,
//!   `final_sigmas_type = "zero"`), written from the UniPC paper (Zhao et al. 2023, "UniPC: A
//!   Unified Predictor-Corrector Framework for Fast Sampling of Diffusion Models") and that
//!   scheduler's documented behaviour; timesteps are integers.
//! - Euler reproduces `FlowMatchEulerDiscreteScheduler(shift)`, whose sigmas differ slightly
//!   (its range ends at the shifted σ of training timestep 1, and it shifts twice) and whose
//!   timesteps are not rounded.
//! - DiffSynth's Euler reproduces the sampler C4G's own refinement pipeline runs (DiffSynth-Studio's
//!   `FlowMatchScheduler` as its Wan pipelines set it: sigmas from exactly 1, shifted once, timesteps
//!   not rounded).

use crate::{RefinerError, Result};

/// Training timesteps of the model: timesteps are `σ · 1000`.
pub const TRAIN_TIMESTEPS: usize = 1000;

/// Which solver turns velocities into the next sample.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Default)]
pub enum Sampler {
    /// UniPC multistep, order 2 (`bh2`) with its corrector: Wan's default, better per step.
    #[default]
    UniPc,
    /// First-order Euler: `x_next = x + (σ_next − σ)·v`.
    Euler,
    /// The same Euler step on DiffSynth's "Wan" schedule ([`Schedule::diffsynth`]): C4G's
    /// layout's default.
    DiffSynthEuler,
}

/// The noise levels of one run: `steps + 1` sigmas ending at 0, and the timestep the model sees at
/// each step.
#[derive(Debug, Clone, PartialEq)]
pub struct Schedule {
    sigmas: Vec<f32>,
    timesteps: Vec<f32>,
}

impl Schedule {
    /// The schedule diffusers' `UniPCMultistepScheduler` (0.42, `use_flow_sigmas`) sets for `steps`
    /// steps: the reference pipeline's UniPC runs.
    ///
    /// Base sigmas `linspace(1, 1/1000, steps + 1)[:-1]`, each shifted by
    /// `σ' = shift·σ / (1 + (shift − 1)·σ)`, the first lowered by 1e-6 when it is 1 (UniPC takes
    /// `ln(1 − σ)`), then a final 0. Timesteps are `σ'·1000` truncated to an integer, as the
    /// scheduler hands them to the model. Sigmas are computed in f64 and stored in f32.
    pub fn unipc(steps: usize, shift: f64) -> Result<Self> {
        check_steps_and_shift(steps, shift)?;
        let mut shifted: Vec<f64> = (0..steps)
            .map(|k| {
                shift_sigma(
                    linspace(1.0, 1.0 / TRAIN_TIMESTEPS as f64, steps + 1, k),
                    shift,
                )
            })
            .collect();
        const EPS: f64 = 1e-6;
        if (shifted[0] - 1.0).abs() < EPS {
            shifted[0] -= EPS;
        }
        Ok(Self::truncated(&shifted))
    }

    /// The original Wan sampler's schedule (`FlowUniPCMultistepScheduler` in Wan2.1): base sigmas
    /// `linspace(0.999, 0, steps + 1)[:-1]`, shifted; integer timesteps. It is the test vector of
    /// WAN_VACE.md (4 steps, shift 5: 0.9998, 0.937265, 0.833055, 0.624687; timesteps 999, 937,
    /// 833, 624) and differs from diffusers' [`unipc`](Self::unipc) by up to 1/steps in base σ.
    pub fn wan(steps: usize, shift: f64) -> Result<Self> {
        check_steps_and_shift(steps, shift)?;
        let sigma_max = 1.0 - 1.0 / TRAIN_TIMESTEPS as f64;
        let shifted: Vec<f64> = (0..steps)
            .map(|k| shift_sigma(linspace(sigma_max, 0.0, steps + 1, k), shift))
            .collect();
        Ok(Self::truncated(&shifted))
    }

    /// f32 sigmas plus a final 0, and timesteps `trunc(σ·1000)`.
    fn truncated(shifted: &[f64]) -> Self {
        let train = TRAIN_TIMESTEPS as f64;
        let mut sigmas: Vec<f32> = shifted.iter().map(|&s| s as f32).collect();
        sigmas.push(0.0);
        let timesteps = shifted
            .iter()
            .map(|&s| (s * train).trunc() as f32)
            .collect();
        Self { sigmas, timesteps }
    }

    /// The schedule diffusers' `FlowMatchEulerDiscreteScheduler(shift)` sets for `steps` steps: the
    /// reference pipeline's Euler runs.
    ///
    /// That scheduler spans the training range `[σ_min, σ_max]` (the shifted sigmas of training
    /// timesteps 1 and 1000, computed in f32), places `steps` timesteps evenly between them, and
    /// shifts again; timesteps are the f32 sigmas times 1000, not rounded.
    pub fn flow_match_euler(steps: usize, shift: f64) -> Result<Self> {
        check_steps_and_shift(steps, shift)?;
        let train = TRAIN_TIMESTEPS as f64;
        // The training sigmas are f32 tensors shifted with f32 arithmetic.
        let shift_f32 = |s: f32| (shift as f32 * s) / (1.0 + (shift - 1.0) as f32 * s);
        let sigma_max = f64::from(shift_f32(1.0));
        let sigma_min = f64::from(shift_f32(1.0 / TRAIN_TIMESTEPS as f32));
        let (start, stop) = (sigma_max * train, sigma_min * train);
        let mut sigmas: Vec<f32> = (0..steps)
            .map(|k| shift_sigma(linspace(start, stop, steps, k) / train, shift) as f32)
            .collect();
        let timesteps = sigmas.iter().map(|&s| s * TRAIN_TIMESTEPS as f32).collect();
        sigmas.push(0.0);
        Ok(Self { sigmas, timesteps })
    }

    /// The schedule DiffSynth-Studio's `FlowMatchScheduler` sets for its Wan pipelines
    /// (`sigma_max` 1, `sigma_min` 0, `extra_one_step`), which C4G's refinement pipeline runs:
    /// base sigmas `linspace(1, 0, steps + 1)[:-1]`, shifted once, then a final 0; timesteps are
    /// `σ'·1000`, not rounded. Computed in f64, stored in f32.
    pub fn diffsynth(steps: usize, shift: f64) -> Result<Self> {
        check_steps_and_shift(steps, shift)?;
        let train = TRAIN_TIMESTEPS as f64;
        let shifted: Vec<f64> = (0..steps)
            .map(|k| shift_sigma(linspace(1.0, 0.0, steps + 1, k), shift))
            .collect();
        let mut sigmas: Vec<f32> = shifted.iter().map(|&s| s as f32).collect();
        sigmas.push(0.0);
        let timesteps = shifted.iter().map(|&s| (s * train) as f32).collect();
        Ok(Self { sigmas, timesteps })
    }

    /// The schedule the reference pipeline runs `sampler` on: [`unipc`](Self::unipc) for UniPC,
    /// [`flow_match_euler`](Self::flow_match_euler) for Euler, [`diffsynth`](Self::diffsynth)
    /// for DiffSynth's Euler.
    pub fn for_sampler(sampler: Sampler, steps: usize, shift: f64) -> Result<Self> {
        match sampler {
            Sampler::UniPc => Self::unipc(steps, shift),
            Sampler::Euler => Self::flow_match_euler(steps, shift),
            Sampler::DiffSynthEuler => Self::diffsynth(steps, shift),
        }
    }

    /// A schedule from explicit sigmas (decreasing, ending at 0) and timesteps (one per step):
    /// for replaying a reference run.
    pub fn from_parts(sigmas: Vec<f32>, timesteps: Vec<f32>) -> Result<Self> {
        let valid = sigmas.len() >= 2
            && timesteps.len() + 1 == sigmas.len()
            && sigmas.last() == Some(&0.0)
            && sigmas.windows(2).all(|w| w[0] > w[1])
            && sigmas[0] <= 1.0;
        if !valid {
            return Err(RefinerError::InvalidRequest(format!(
                "a schedule needs decreasing sigmas in (0, 1] ending at 0 and one timestep per step, got sigmas {sigmas:?} and timesteps {timesteps:?}"
            )));
        }
        Ok(Self { sigmas, timesteps })
    }

    /// Number of steps (model evaluations per guidance branch).
    pub fn steps(&self) -> usize {
        self.timesteps.len()
    }

    /// `steps + 1` noise levels, the last 0.
    pub fn sigmas(&self) -> &[f32] {
        &self.sigmas
    }

    /// The timestep fed to the model at each step.
    pub fn timesteps(&self) -> &[f32] {
        &self.timesteps
    }
}

/// Point `k` of numpy's `linspace(start, stop, num)`: `start + k·step`, the last exactly `stop`.
fn linspace(start: f64, stop: f64, num: usize, k: usize) -> f64 {
    if num > 1 && k + 1 == num {
        stop
    } else if num > 1 {
        start + k as f64 * ((stop - start) / (num - 1) as f64)
    } else {
        start
    }
}

/// The timestep shift `shift·σ / (1 + (shift − 1)·σ)`.
fn shift_sigma(sigma: f64, shift: f64) -> f64 {
    shift * sigma / (1.0 + (shift - 1.0) * sigma)
}

fn check_steps_and_shift(steps: usize, shift: f64) -> Result<()> {
    if steps == 0 {
        return Err(RefinerError::InvalidRequest(
            "steps must be at least 1".to_owned(),
        ));
    }
    if !(shift.is_finite() && shift > 0.0) {
        return Err(RefinerError::InvalidRequest(format!(
            "shift must be a positive finite number, got {shift}"
        )));
    }
    Ok(())
}

/// A sampler walking one schedule: call [`step`](Self::step) once per step with the model's
/// velocity at the current sample.
#[derive(Debug, Clone)]
pub struct Solver {
    schedule: Schedule,
    step: usize,
    method: Method,
}

#[derive(Debug, Clone)]
enum Method {
    Euler,
    UniPc(UniPcState),
}

/// What UniPC carries between steps.
#[derive(Debug, Clone, Default)]
struct UniPcState {
    /// x0 predictions of the last two steps, newest last.
    previous_x0: Vec<Vec<f32>>,
    /// The (corrected) sample the last predictor started from.
    last_sample: Option<Vec<f32>>,
    /// The order the last predictor used; the corrector of the next step uses the same.
    last_order: usize,
}

impl Solver {
    /// A fresh solver at the start of `schedule`.
    pub fn new(sampler: Sampler, schedule: Schedule) -> Self {
        let method = match sampler {
            Sampler::Euler | Sampler::DiffSynthEuler => Method::Euler,
            Sampler::UniPc => Method::UniPc(UniPcState::default()),
        };
        Self {
            schedule,
            step: 0,
            method,
        }
    }

    /// The schedule being walked.
    pub fn schedule(&self) -> &Schedule {
        &self.schedule
    }

    /// Index of the next step.
    pub fn current_step(&self) -> usize {
        self.step
    }

    /// Advances `sample` (the sample at the current step) one step, given the model's velocity
    /// there, and returns the sample at the next noise level.
    pub fn step(&mut self, velocity: &[f32], sample: &[f32]) -> Result<Vec<f32>> {
        let steps = self.schedule.steps();
        if self.step >= steps {
            return Err(RefinerError::InvalidRequest(format!(
                "the schedule has {steps} steps and all of them have run"
            )));
        }
        if velocity.len() != sample.len() {
            return Err(RefinerError::InvalidRequest(format!(
                "velocity has {} values, the sample {}",
                velocity.len(),
                sample.len()
            )));
        }
        let i = self.step;
        let sigmas = &self.schedule.sigmas;
        let next = match &mut self.method {
            Method::Euler => euler(sample, velocity, sigmas[i], sigmas[i + 1]),
            Method::UniPc(state) => state.step(sigmas, i, steps, velocity, sample),
        };
        self.step += 1;
        Ok(next)
    }
}

fn euler(sample: &[f32], velocity: &[f32], sigma: f32, sigma_next: f32) -> Vec<f32> {
    let dt = sigma_next - sigma;
    sample
        .iter()
        .zip(velocity)
        .map(|(&x, &v)| x + dt * v)
        .collect()
}

/// `λ(σ) = ln(α) − ln(σ)` with `α = 1 − σ`: the log signal-to-noise ratio UniPC steps in.
fn lambda(sigma: f32) -> f64 {
    let s = f64::from(sigma);
    (1.0 - s).ln() - s.ln()
}

impl UniPcState {
    fn step(
        &mut self,
        sigmas: &[f32],
        i: usize,
        steps: usize,
        velocity: &[f32],
        sample: &[f32],
    ) -> Vec<f32> {
        let sigma = sigmas[i];
        let x0: Vec<f32> = sample
            .iter()
            .zip(velocity)
            .map(|(&x, &v)| x - sigma * v)
            .collect();
        // The corrector refines the sample the last predictor produced, using this step's model
        // output; the predictor then starts from the corrected sample.
        let corrected = match &self.last_sample {
            Some(last) if i > 0 => Some(self.correct(sigmas, i, last, &x0)),
            _ => None,
        };
        let sample = corrected.as_deref().unwrap_or(sample);

        if self.previous_x0.len() == 2 {
            self.previous_x0.remove(0);
        }
        self.previous_x0.push(x0);
        // Order 1 to warm up (one x0 in history) and on the last step (`lower_order_final`).
        let order = 2.min(steps - i).min(self.previous_x0.len());
        let next = self.predict(sigmas, i, sample, order);
        self.last_order = order;
        self.last_sample = Some(sample.to_vec());
        next
    }

    /// UniP-`order` from σ_i to σ_{i+1}, with the newest x0 prediction `m0` and (order 2) the one
    /// before.
    fn predict(&self, sigmas: &[f32], i: usize, x: &[f32], order: usize) -> Vec<f32> {
        let (sigma_s0, sigma_t) = (sigmas[i], sigmas[i + 1]);
        let h = lambda(sigma_t) - lambda(sigma_s0);
        let hh = -h;
        let h_phi_1 = hh.exp_m1();
        let b_h = hh.exp_m1();
        let alpha_t = 1.0 - f64::from(sigma_t);
        let ratio = f64::from(sigma_t) / f64::from(sigma_s0);
        let m0 = &self.previous_x0[self.previous_x0.len() - 1];
        let a = ratio as f32;
        let b = (-alpha_t * h_phi_1) as f32;
        if order == 1 {
            return x.iter().zip(m0).map(|(&x, &m)| a * x + b * m).collect();
        }
        // Order 2: the divided difference to the previous x0, with the paper's simplified ρ = ½.
        let m1 = &self.previous_x0[self.previous_x0.len() - 2];
        let rk = (lambda(sigmas[i - 1]) - lambda(sigma_s0)) / h;
        let c = (-alpha_t * b_h * 0.5 / rk) as f32;
        x.iter()
            .zip(m0)
            .zip(m1)
            .map(|((&x, &m0), &m1)| a * x + b * m0 + c * (m1 - m0))
            .collect()
    }

    /// UniC-`last_order` at σ_i: `last` is the sample at σ_{i−1}, `this_x0` the x0 predicted at
    /// σ_i from the predictor's sample.
    fn correct(&self, sigmas: &[f32], i: usize, last: &[f32], this_x0: &[f32]) -> Vec<f32> {
        let order = self.last_order;
        let (sigma_s0, sigma_t) = (sigmas[i - 1], sigmas[i]);
        let h = lambda(sigma_t) - lambda(sigma_s0);
        let hh = -h;
        let h_phi_1 = hh.exp_m1();
        let b_h = hh.exp_m1();
        let alpha_t = 1.0 - f64::from(sigma_t);
        let ratio = f64::from(sigma_t) / f64::from(sigma_s0);
        // b_k = k!·h_φ_k / B(h) with h_φ_1 = e^hh − 1 and h_φ_{k+1} = h_φ_k / hh − 1/(k+1)!.
        let phi_1 = h_phi_1 / hh - 1.0;
        let b1 = phi_1 / b_h;
        let b2 = (phi_1 / hh - 0.5) * 2.0 / b_h;
        let m0 = &self.previous_x0[self.previous_x0.len() - 1];
        let a = ratio as f32;
        let b = (-alpha_t * h_phi_1) as f32;
        if order == 1 {
            let c = (-alpha_t * b_h * 0.5) as f32;
            return last
                .iter()
                .zip(m0)
                .zip(this_x0)
                .map(|((&x, &m0), &mt)| a * x + b * m0 + c * (mt - m0))
                .collect();
        }
        // Order 2: solve [[1, 1], [r, 1]]·ρ = [b1, b2] for the weights of the previous divided
        // difference and of this step's.
        let m1 = &self.previous_x0[self.previous_x0.len() - 2];
        let rk = (lambda(sigmas[i - 2]) - lambda(sigma_s0)) / h;
        let rho_0 = (b1 - b2) / (1.0 - rk);
        let rho_1 = b1 - rho_0;
        let c_prev = (-alpha_t * b_h * rho_0 / rk) as f32;
        let c_this = (-alpha_t * b_h * rho_1) as f32;
        last.iter()
            .zip(m0)
            .zip(m1)
            .zip(this_x0)
            .map(|(((&x, &m0), &m1), &mt)| a * x + b * m0 + c_prev * (m1 - m0) + c_this * (mt - m0))
            .collect()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_diffsynth_schedule_starts_at_one_and_shifts_once() {
        // linspace(1, 0, 5)[:-1] = [1, 0.75, 0.5, 0.25], shifted by 5: [1, 0.9375, 5/6, 0.625].
        let s = Schedule::diffsynth(4, 5.0).unwrap();
        let expected = [1.0, 0.9375, 5.0 / 6.0, 0.625, 0.0];
        for (got, want) in s.sigmas().iter().zip(expected) {
            assert!((f64::from(*got) - want).abs() < 1e-7, "{:?}", s.sigmas());
        }
        assert_eq!(s.timesteps()[0], 1000.0);
        assert_eq!(s.timesteps()[3], 625.0);
        assert!((s.timesteps()[2] - 833.333_3).abs() < 1e-3);
        assert_eq!(
            Schedule::for_sampler(Sampler::DiffSynthEuler, 4, 5.0).unwrap(),
            s
        );
    }

    #[test]
    fn the_wan_schedule_matches_the_documented_test_vector() {
        let s = Schedule::wan(4, 5.0).unwrap();
        let expected = [0.9998, 0.937265, 0.833055, 0.624687, 0.0];
        assert_eq!(s.sigmas().len(), 5);
        for (got, want) in s.sigmas().iter().zip(expected) {
            assert!((got - want).abs() < 1e-6, "{:?}", s.sigmas());
        }
        assert_eq!(s.timesteps(), &[999.0, 937.0, 833.0, 624.0]);
    }

    #[test]
    fn shift_one_leaves_the_base_sigmas() {
        let s = Schedule::wan(4, 1.0).unwrap();
        let expected = [0.999, 0.74925, 0.4995, 0.24975, 0.0];
        for (got, want) in s.sigmas().iter().zip(expected) {
            assert!((got - want).abs() < 1e-7, "{:?}", s.sigmas());
        }
    }

    #[test]
    fn zero_steps_and_bad_shifts_are_refused() {
        assert!(Schedule::wan(0, 3.0).is_err());
        for sampler in [Sampler::UniPc, Sampler::Euler] {
            assert!(Schedule::for_sampler(sampler, 0, 3.0).is_err());
            assert!(Schedule::for_sampler(sampler, 4, 0.0).is_err());
            assert!(Schedule::for_sampler(sampler, 4, f64::NAN).is_err());
        }
    }

    #[test]
    fn the_unipc_schedule_starts_just_below_one() {
        let s = Schedule::unipc(4, 5.0).unwrap();
        let expected = [0.999999, 0.937578, 0.833611, 0.625936, 0.0];
        for (got, want) in s.sigmas().iter().zip(expected) {
            assert!((got - want).abs() < 1e-6, "{:?}", s.sigmas());
        }
        assert_eq!(s.timesteps(), &[999.0, 937.0, 833.0, 625.0]);
    }

    #[test]
    fn the_euler_schedule_spans_the_shifted_training_range_and_shifts_again() {
        let s = Schedule::flow_match_euler(4, 5.0).unwrap();
        let sigma_min = 5.0 * 0.001 / (1.0 + 4.0 * 0.001);
        // Evenly spaced in [σ_min, 1], then shifted: the first is 1, the last shift(σ_min).
        let base = |k: f64| 1.0 + k * (sigma_min - 1.0) / 3.0;
        let shift = |x: f64| 5.0 * x / (1.0 + 4.0 * x);
        for (k, got) in s.sigmas()[..4].iter().enumerate() {
            assert!(
                (f64::from(*got) - shift(base(k as f64))).abs() < 1e-6,
                "{:?}",
                s.sigmas()
            );
        }
        assert_eq!(s.sigmas()[4], 0.0);
        assert_eq!(s.timesteps()[0], 1000.0);
        assert_eq!(s.timesteps()[1], s.sigmas()[1] * 1000.0);
        assert_eq!(
            Schedule::flow_match_euler(1, 3.0).unwrap().sigmas(),
            &[1.0, 0.0]
        );
    }

    #[test]
    fn euler_steps_along_the_velocity() {
        let s = Schedule::wan(2, 1.0).unwrap();
        let (s0, s1) = (s.sigmas()[0], s.sigmas()[1]);
        let mut solver = Solver::new(Sampler::Euler, s);
        let next = solver.step(&[1.0, -2.0], &[0.5, 0.25]).unwrap();
        assert_eq!(next, vec![0.5 + (s1 - s0), 0.25 - 2.0 * (s1 - s0)]);
    }

    /// A velocity field that is exact for a fixed (x0, noise) pair: every solver must land on x0.
    fn exact_run(sampler: Sampler, steps: usize) -> (Vec<f32>, Vec<f32>) {
        let x0 = vec![0.3f32, -1.2, 2.0];
        let noise = vec![1.0f32, 0.5, -0.7];
        let v: Vec<f32> = noise.iter().zip(&x0).map(|(n, x)| n - x).collect();
        let schedule = Schedule::for_sampler(sampler, steps, 3.0).unwrap();
        let s0 = schedule.sigmas()[0];
        let mut x: Vec<f32> = x0
            .iter()
            .zip(&noise)
            .map(|(x, n)| (1.0 - s0) * x + s0 * n)
            .collect();
        let mut solver = Solver::new(sampler, schedule);
        for _ in 0..steps {
            x = solver.step(&v, &x).unwrap();
        }
        (x, x0)
    }

    #[test]
    fn straight_flows_are_integrated_exactly_by_both_samplers() {
        for sampler in [Sampler::Euler, Sampler::UniPc] {
            for steps in [1, 2, 3, 7] {
                let (x, x0) = exact_run(sampler, steps);
                for (a, b) in x.iter().zip(&x0) {
                    assert!((a - b).abs() < 1e-5, "{sampler:?} {steps}: {x:?} vs {x0:?}");
                }
            }
        }
    }

    #[test]
    fn stepping_past_the_end_is_an_error() {
        let mut solver = Solver::new(Sampler::UniPc, Schedule::unipc(1, 3.0).unwrap());
        solver.step(&[0.0], &[1.0]).unwrap();
        assert!(solver.step(&[0.0], &[1.0]).is_err());
    }
}
