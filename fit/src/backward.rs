//! The gradient of a fitted scene's interpolation: from a loss's gradient with respect to the set
//! at time `t` (what the renderer's backward pass returns, in the optimiser's parametrisation) to
//! its gradient with respect to every keyframe's parameters.
//!
//! Per quantity, following the engine's rules ([`crate::scene`]):
//! - **positions** are linear in the keyframe positions: a cubic Hermite segment whose Bessel
//!   tangents are themselves linear in the positions, so `p(t) = Σ_k c_k(t)·p_k`. The weights
//!   `c_k(t)` are read off the engine's own track by linearity (a probe track whose Gaussian `j`
//!   sits at 1 on keyframe `j` and 0 elsewhere: its position at `t` is `c_j(t)`), so they are the
//!   engine's rule, rounded to f32, not a copy of it;
//! - **log scales** are `(1 − s)·ln a + s·ln b` between the bracketing keyframes at fraction `s`;
//!   **colour** is linear the same way;
//! - **opacity** is linear in opacity, not in its logit: `∂L/∂θ_a = (1 − s)·σ'(θ_a)·∂L/∂o_t`, with
//!   `∂L/∂o_t` recovered from the renderer's logit gradient over `o_t(1 − o_t)` (0 where that is
//!   0: the renderer's gradient is then 0 too);
//! - **rotations**: `u = w_a(θ)·â ± w_b(θ)·b̂` with slerp's weights `w_a = sin((1 − s)θ)/sin θ`,
//!   `w_b = sin(sθ)/sin θ` of the arc angle `cos θ = |â·b̂|`, then normalised: the gradient goes
//!   through the output's normalisation, the weights (through θ) and each keyframe quaternion's
//!   normalisation, exactly. Where the engine takes the straight line (`cos θ > 0.9995`) its
//!   weights are the constants `1 − s`, `s`, and so are ours.
//!
//! At a keyframe time the set is that keyframe's, so every gradient goes to it alone.

use c4g_engine::KeyframeTrack;
use c4g_optim::Group;
use c4g_renderer::GaussianGradients;
use c4g_scene::GaussianSet;

use crate::error::FitError;
use crate::keyframe_params::KeyframeParams;

/// How the set at one time is made from the keyframes.
#[derive(Debug, Clone, PartialEq)]
pub struct Blend {
    /// The keyframe at or before `t`.
    pub lower: usize,
    /// The keyframe after `t` (equal to `lower` at a keyframe time).
    pub upper: usize,
    /// The fraction of the way from `lower` to `upper` (0 at a keyframe time).
    pub s: f64,
    /// `c_k(t)`, one per keyframe: the position at `t` is `Σ_k c_k(t)·p_k`.
    pub position: Vec<f64>,
}

impl Blend {
    /// The blend at `t` of keyframes at `times` (strictly increasing). Fails outside their span.
    pub fn new(times: &[f64], t: f64) -> Result<Self, FitError> {
        let (Some(&first), Some(&last)) = (times.first(), times.last()) else {
            return Err(FitError::Invalid("no keyframes".into()));
        };
        if !(t >= first && t <= last) {
            return Err(FitError::Invalid(format!(
                "t = {t} is outside the keyframes' span [{first}, {last}]"
            )));
        }
        let at = times.partition_point(|&x| x < t);
        let (lower, upper, s) = if times[at] == t {
            (at, at, 0.0)
        } else {
            (
                at - 1,
                at,
                (t - times[at - 1]) / (times[at] - times[at - 1]),
            )
        };
        Ok(Self {
            lower,
            upper,
            s,
            position: position_weights(times, t)?,
        })
    }

    /// The weight of the lower and upper keyframe in the linear rules (`1 − s`, `s`).
    fn pair(&self) -> [(usize, f64); 2] {
        if self.lower == self.upper {
            [(self.lower, 1.0), (self.upper, 0.0)]
        } else {
            [(self.lower, 1.0 - self.s), (self.upper, self.s)]
        }
    }
}

/// `c_k(t)` by probing the engine's track: K Gaussians, Gaussian `j` at x = 1 on keyframe `j`.
fn position_weights(times: &[f64], t: f64) -> Result<Vec<f64>, FitError> {
    let k = times.len();
    let probe = |key: usize| {
        GaussianSet::new(
            (0..k)
                .map(|j| [f32::from(u8::from(j == key)), 0.0, 0.0])
                .collect(),
            vec![[1.0; 3]; k],
            vec![[1.0, 0.0, 0.0, 0.0]; k],
            vec![0.5; k],
            vec![[0.0; 3]; k],
        )
    };
    let keyframes = (0..k)
        .map(|key| Ok((times[key], probe(key)?)))
        .collect::<Result<Vec<_>, FitError>>()?;
    let at = KeyframeTrack::new(keyframes)?.at(t)?;
    Ok(at.positions().iter().map(|p| f64::from(p[0])).collect())
}

fn sigmoid(x: f64) -> f64 {
    1.0 / (1.0 + (-x).exp())
}

/// Unit quaternion and norm (a zero one is the identity, with norm 1, as the engine treats it).
fn unit(q: [f64; 4]) -> ([f64; 4], f64) {
    let n = q.iter().map(|v| v * v).sum::<f64>().sqrt();
    if n > 0.0 && n.is_finite() {
        (q.map(|v| v / n), n)
    } else {
        ([1.0, 0.0, 0.0, 0.0], 1.0)
    }
}

/// `(I − q̂q̂ᵀ)·g / n`: a gradient through the normalisation of a quaternion of norm `n`.
fn through_normalisation(unit_q: [f64; 4], norm: f64, g: [f64; 4]) -> [f64; 4] {
    let dot: f64 = (0..4).map(|j| unit_q[j] * g[j]).sum();
    std::array::from_fn(|j| (g[j] - dot * unit_q[j]) / norm)
}

/// Slerp's weights at `s` for unit quaternions `a`, `b` (the engine's, including its straight-line
/// case), the sign `b` is taken with (the short arc), and the weights' derivatives with respect to
/// `a` and `b` (through the arc angle θ, `cos θ = ±a·b`; zero in the straight-line case, where the
/// engine's weights are the constants `1 − s`, `s`).
struct SlerpWeights {
    a: f64,
    b: f64,
    sign: f64,
    /// `∂w_a/∂a`, `∂w_b/∂a`, `∂w_a/∂b`, `∂w_b/∂b`.
    d: [[f64; 4]; 4],
}

fn slerp_weights(a: [f64; 4], b: [f64; 4], s: f64) -> SlerpWeights {
    let mut dot: f64 = (0..4).map(|j| a[j] * b[j]).sum();
    let sign = if dot < 0.0 { -1.0 } else { 1.0 };
    dot *= sign;
    if dot > 0.9995 {
        return SlerpWeights {
            a: 1.0 - s,
            b: s,
            sign,
            d: [[0.0; 4]; 4],
        };
    }
    let theta = dot.min(1.0).acos();
    let (sin, cos) = theta.sin_cos();
    let weight = |f: f64| (f * theta).sin() / sin;
    // d/dθ of sin(fθ)/sin θ.
    let slope = |f: f64| (f * (f * theta).cos() * sin - (f * theta).sin() * cos) / (sin * sin);
    let (da, db) = (slope(1.0 - s), slope(s));
    // θ = acos(±a·b): ∂θ/∂a = ∓b / sin θ, ∂θ/∂b = ∓a / sin θ.
    let theta_a = b.map(|v| -sign * v / sin);
    let theta_b = a.map(|v| -sign * v / sin);
    SlerpWeights {
        a: weight(1.0 - s),
        b: weight(s),
        sign,
        d: [
            theta_a.map(|v| da * v),
            theta_a.map(|v| db * v),
            theta_b.map(|v| da * v),
            theta_b.map(|v| db * v),
        ],
    }
}

/// Adds to `out` (the layout of `params`) the gradient with respect to the keyframe parameters
/// of a loss whose gradient with respect to `rendered` (the set at the blend's time, made from
/// `params`) is `grads`.
pub fn chain(
    blend: &Blend,
    params: &KeyframeParams,
    rendered: &GaussianSet,
    grads: &GaussianGradients,
    out: &mut KeyframeParams,
) {
    let n = params.gaussians();
    let pair = blend.pair();
    for i in 0..n {
        for (k, &c) in blend.position.iter().enumerate() {
            if c != 0.0 {
                for j in 0..3 {
                    *out.value_mut(Group::Position, i, k, j) +=
                        c * f64::from(grads.positions[i][j]);
                }
            }
        }
        for &(k, w) in &pair {
            for j in 0..3 {
                *out.value_mut(Group::LogScale, i, k, j) += w * f64::from(grads.log_scales[i][j]);
                *out.value_mut(Group::Color, i, k, j) += w * f64::from(grads.colors[i][j]);
            }
        }
        chain_opacity(
            blend,
            params,
            rendered.opacities()[i],
            grads.opacity_logits[i],
            i,
            out,
        );
        chain_rotation(
            blend,
            params,
            rendered.rotations()[i],
            grads.rotations[i],
            i,
            out,
        );
    }
}

fn chain_opacity(
    blend: &Blend,
    params: &KeyframeParams,
    rendered: f32,
    grad_logit: f32,
    i: usize,
    out: &mut KeyframeParams,
) {
    let o = f64::from(rendered);
    let slope = o * (1.0 - o);
    if slope <= 0.0 || grad_logit == 0.0 {
        return;
    }
    let d_opacity = f64::from(grad_logit) / slope;
    for (k, w) in blend.pair() {
        let ok = sigmoid(params.value(Group::OpacityLogit, i, k, 0));
        *out.value_mut(Group::OpacityLogit, i, k, 0) += w * ok * (1.0 - ok) * d_opacity;
    }
}

fn chain_rotation(
    blend: &Blend,
    params: &KeyframeParams,
    rendered: [f32; 4],
    grad: [f32; 4],
    i: usize,
    out: &mut KeyframeParams,
) {
    if blend.lower == blend.upper {
        // At a keyframe time the rendered quaternion is the keyframe's stored one.
        add_rotation(out, i, blend.lower, grad.map(f64::from));
        return;
    }
    // The renderer's gradient is with respect to the rendered quaternion through its norm r:
    // r·g is the gradient with respect to its direction (r is 1 but where the engine returns a
    // stored quaternion as is, when both keyframes hold the same bits).
    let (_, r) = unit(rendered.map(f64::from));
    let g = grad.map(|v| r * f64::from(v));
    let quat = |k: usize| std::array::from_fn(|j| params.value(Group::Rotation, i, k, j));
    let (a, na) = unit(quat(blend.lower));
    let (b, nb) = unit(quat(blend.upper));
    let w = slerp_weights(a, b, blend.s);
    let u: [f64; 4] = std::array::from_fn(|j| w.a * a[j] + w.sign * w.b * b[j]);
    let (u_unit, u_norm) = unit(u);
    // ∂L/∂u, then u = w_a(θ)·â ± w_b(θ)·b̂ to each unit quaternion, then its normalisation.
    let du = through_normalisation(u_unit, u_norm, g);
    let along_a: f64 = (0..4).map(|j| du[j] * a[j]).sum();
    let along_b: f64 = (0..4).map(|j| du[j] * w.sign * b[j]).sum();
    let d_a: [f64; 4] =
        std::array::from_fn(|j| w.a * du[j] + along_a * w.d[0][j] + along_b * w.d[1][j]);
    let d_b: [f64; 4] =
        std::array::from_fn(|j| w.sign * w.b * du[j] + along_a * w.d[2][j] + along_b * w.d[3][j]);
    add_rotation(out, i, blend.lower, through_normalisation(a, na, d_a));
    add_rotation(out, i, blend.upper, through_normalisation(b, nb, d_b));
}

fn add_rotation(out: &mut KeyframeParams, i: usize, k: usize, d: [f64; 4]) {
    for (j, v) in d.into_iter().enumerate() {
        *out.value_mut(Group::Rotation, i, k, j) += v;
    }
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]
    use super::*;
    use crate::scene::FittedScene;
    use c4g_optim::Params;

    /// Four keyframes of six Gaussians: rotations 11° to 34° apart from one keyframe to the next
    /// (Gaussians 0 to 2), one stored with its sign flipping between keyframes and a norm of 1.5
    /// (3: the short arc and the normalisation), one turning 0.1° a keyframe (4: the engine's
    /// straight-line case), one holding the same bits of norm 1.5 at every keyframe (5: the
    /// engine returns them as stored).
    fn keyframes() -> (Vec<f64>, KeyframeParams) {
        let times = vec![0.0, 0.3, 0.8, 1.0];
        let sets: Vec<GaussianSet> = (0..4)
            .map(|k| {
                let kf = k as f32;
                let f = |i: usize, w: f32| ((i as f32 + 1.0) * w + 0.7 * kf).sin();
                GaussianSet::new(
                    (0..6)
                        .map(|i| [f(i, 1.0), f(i, 1.3), 2.0 + 0.3 * f(i, 0.9)])
                        .collect(),
                    (0..6)
                        .map(|i| [0.1 + 0.05 * f(i, 2.0), 0.2, 0.05 + 0.02 * f(i, 3.0)])
                        .collect(),
                    (0..6)
                        .map(|i| {
                            // Half the angle turned since keyframe 0.
                            let half = [0.1, 0.2, 0.3, 0.2, 0.001, 0.0][i] * kf;
                            let (s, c) = half.sin_cos();
                            let stored = match i {
                                3 if k % 2 == 1 => -1.5,
                                5 => 1.5,
                                _ => 1.0,
                            };
                            [c, 0.6 * s, 0.8 * s, 0.0].map(|v| v * stored)
                        })
                        .collect(),
                    (0..6).map(|i| 0.5 + 0.3 * f(i, 1.7)).collect(),
                    (0..6).map(|i| [0.5 + 0.4 * f(i, 0.5), 0.3, 0.6]).collect(),
                )
                .unwrap()
            })
            .collect();
        (times, KeyframeParams::from_sets(&sets).unwrap())
    }

    /// A fixed linear functional of the set at `t` in the optimiser's parametrisation (rotations
    /// normalised, as the renderer reads them), and its gradient in the renderer's layout.
    fn weights(i: usize, j: usize) -> f64 {
        ((i * 14 + j) as f64 * 0.77).sin()
    }

    fn functional(set: &GaussianSet) -> f64 {
        let p = Params::from_set(set).unwrap();
        let mut total = 0.0;
        for i in 0..set.len() {
            let mut row = p.row(i);
            let (q, _) = unit([row[6], row[7], row[8], row[9]]);
            row[6..10].copy_from_slice(&q);
            total += (0..14).map(|j| weights(i, j) * row[j]).sum::<f64>();
        }
        total
    }

    fn functional_gradient(set: &GaussianSet) -> GaussianGradients {
        let mut g = GaussianGradients::zeros(set.len());
        for i in 0..set.len() {
            let w = |j: usize| weights(i, j) as f32;
            g.positions[i] = [w(0), w(1), w(2)];
            g.log_scales[i] = [w(3), w(4), w(5)];
            let (q, n) = unit(set.rotations()[i].map(f64::from));
            let r = through_normalisation(q, n, [6, 7, 8, 9].map(|j| weights(i, j)));
            g.rotations[i] = r.map(|v| v as f32);
            g.opacity_logits[i] = w(10);
            g.colors[i] = [w(11), w(12), w(13)];
        }
        g
    }

    /// Central differences of the functional of the engine's `at(t)` over every keyframe
    /// parameter, against [`chain`]. The sums are f64; `at(t)` itself is the engine's f32 set, so a
    /// step of 1e-3 leaves a rounding error near 6e-8 / 1e-3 ≈ 1e-4 of a value's size (measured:
    /// at most 1.2e-4): the
    /// tolerance is 5e-4 absolute plus 1e-3 relative, for rotations too (measured: 1.3e-5).
    #[test]
    fn the_chained_gradient_matches_finite_differences_of_at() {
        let (times, params) = keyframes();
        for t in [0.0, 0.1, 0.3, 0.55, 0.93, 1.0] {
            let scene = |p: &KeyframeParams| FittedScene {
                times: times.clone(),
                sets: p.sets(),
                static_mask: vec![false; 6],
            };
            let rendered = scene(&params).at(t).unwrap();
            let blend = Blend::new(&times, t).unwrap();
            let mut analytic = KeyframeParams::from_sets(&params.sets()).unwrap();
            for g in Group::ALL {
                analytic.params.group_mut(g).fill(0.0);
            }
            chain(
                &blend,
                &params,
                &rendered,
                &functional_gradient(&rendered),
                &mut analytic,
            );
            let h = 1e-3;
            for g in Group::ALL {
                for at in 0..params.params.group(g).len() {
                    let eval = |d: f64| {
                        let mut p = params.clone();
                        p.params.group_mut(g)[at] += d;
                        functional(&scene(&p).at(t).unwrap())
                    };
                    let numeric = (eval(h) - eval(-h)) / (2.0 * h);
                    let a = analytic.params.group(g)[at];
                    let tol = 5e-4 + 1e-3 * a.abs();
                    assert!(
                        (a - numeric).abs() <= tol,
                        "t = {t}, {g:?}[{at}]: analytic {a}, numeric {numeric}"
                    );
                }
            }
        }
    }

    #[test]
    fn position_weights_are_the_engines_and_sum_to_one() {
        let (times, _) = keyframes();
        let b = Blend::new(&times, 0.3).unwrap();
        assert_eq!(
            b.position,
            vec![0.0, 1.0, 0.0, 0.0],
            "a keyframe time is that keyframe"
        );
        let b = Blend::new(&times, 0.55).unwrap();
        assert_eq!((b.lower, b.upper), (1, 2));
        // A translation of every keyframe translates the Hermite curve: the weights sum to 1.
        assert!((b.position.iter().sum::<f64>() - 1.0).abs() < 1e-6);
        assert!(Blend::new(&times, 1.2).is_err());
    }
}
