//! Adam (Kingma & Ba) over a scene's parameters, one learning rate per [`Group`], with its state
//! (step, first and second moments) following the Gaussians through densification and saved and
//! resumed as JSON (f64 values round-trip exactly).

use std::path::Path;

use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use crate::params::{Group, Params};
use c4g_scene::SceneError;

/// Values a thread steps at a time.
const CHUNK: usize = 1 << 14;

/// Adam's constants.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct AdamConfig {
    /// Decay of the first moment.
    pub beta1: f64,
    /// Decay of the second moment.
    pub beta2: f64,
    /// Added to the second moment's square root.
    pub eps: f64,
}

impl Default for AdamConfig {
    /// 3DGS's: 0.9, 0.999 and eps 1e-15.
    fn default() -> Self {
        Self {
            beta1: 0.9,
            beta2: 0.999,
            eps: 1e-15,
        }
    }
}

/// The optimiser and its state.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Adam {
    /// The constants.
    pub config: AdamConfig,
    step: u64,
    m: Params,
    v: Params,
}

impl Adam {
    /// A fresh optimiser for `n` Gaussians.
    pub fn new(config: AdamConfig, n: usize) -> Self {
        Self {
            config,
            step: 0,
            m: Params::zeros(n),
            v: Params::zeros(n),
        }
    }

    /// Steps taken.
    pub fn steps(&self) -> u64 {
        self.step
    }

    /// Gaussians it holds state for.
    pub fn len(&self) -> usize {
        self.m.len()
    }

    /// True when it holds none.
    pub fn is_empty(&self) -> bool {
        self.m.is_empty()
    }

    /// One step of `params` down `grads` with each group's rate in `rates` (indexed by
    /// [`Group::index`]; 0 freezes a group).
    pub fn step(
        &mut self,
        params: &mut Params,
        grads: &Params,
        rates: [f64; 5],
    ) -> Result<(), SceneError> {
        if params.len() != self.len() || grads.len() != self.len() {
            return Err(SceneError::LengthMismatch {
                field: "Adam's parameters and gradients",
                expected: self.len(),
                actual: if params.len() != self.len() {
                    params.len()
                } else {
                    grads.len()
                },
            });
        }
        if Group::ALL
            .iter()
            .any(|&g| grads.group(g).par_iter().any(|v| !v.is_finite()))
        {
            return Err(SceneError::InvalidImage(
                "a gradient is not finite: Adam refuses to step".into(),
            ));
        }
        self.step += 1;
        let AdamConfig { beta1, beta2, eps } = self.config;
        let c1 = 1.0 - beta1.powf(self.step as f64);
        let c2 = 1.0 - beta2.powf(self.step as f64);
        // Element by element, so the threads' split cannot change a bit of the result; a fit's
        // per-step work is mostly this and the renderer's, which is threaded too.
        for g in Group::ALL {
            let lr = rates[g.index()];
            let (p, grad) = (params.group_mut(g), grads.group(g));
            let (m, v) = (self.m.group_mut(g), self.v.group_mut(g));
            p.par_chunks_mut(CHUNK)
                .zip(grad.par_chunks(CHUNK))
                .zip(m.par_chunks_mut(CHUNK).zip(v.par_chunks_mut(CHUNK)))
                .for_each(|((p, grad), (m, v))| {
                    for k in 0..p.len() {
                        m[k] = beta1 * m[k] + (1.0 - beta1) * grad[k];
                        v[k] = beta2 * v[k] + (1.0 - beta2) * grad[k] * grad[k];
                        p[k] -= lr * (m[k] / c1) / ((v[k] / c2).sqrt() + eps);
                    }
                });
        }
        Ok(())
    }

    /// Keeps the state of the Gaussians whose entry in `keep` is true (pruning).
    pub fn select(&mut self, keep: &[bool]) {
        self.m = self.m.select(keep);
        self.v = self.v.select(keep);
    }

    /// Appends zeroed state for `k` new Gaussians (clones and split children start afresh).
    pub fn extend(&mut self, k: usize) {
        for _ in 0..k {
            self.m.push(&[0.0; 14]);
            self.v.push(&[0.0; 14]);
        }
    }

    /// Zeroes one group's moments (3DGS does for opacity after resetting it).
    pub fn reset_group(&mut self, group: Group) {
        self.m.group_mut(group).fill(0.0);
        self.v.group_mut(group).fill(0.0);
    }

    /// Writes the state (and, with it, the parameters it steps) to `path` as JSON.
    pub fn save(&self, params: &Params, path: &Path) -> Result<(), SceneError> {
        let text = serde_json::to_string(&(self, params)).map_err(|e| io(path, e.to_string()))?;
        std::fs::write(path, text).map_err(|e| io(path, e.to_string()))
    }

    /// Reads what [`save`](Self::save) wrote.
    pub fn load(path: &Path) -> Result<(Self, Params), SceneError> {
        let text = std::fs::read_to_string(path).map_err(|e| io(path, e.to_string()))?;
        let (adam, params): (Self, Params) =
            serde_json::from_str(&text).map_err(|e| io(path, e.to_string()))?;
        if adam.len() != params.len() {
            return Err(io(path, "optimiser state and parameters disagree".into()));
        }
        Ok((adam, params))
    }
}

fn io(path: &Path, message: String) -> SceneError {
    SceneError::Io {
        path: path.display().to_string(),
        message,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A quadratic bowl `½ Σ (p − t)²` over a few Gaussians' worth of parameters.
    fn bowl(n: usize) -> (Params, Params) {
        let mut t = Params::zeros(n);
        let mut j = 0.0;
        for g in Group::ALL {
            for v in t.group_mut(g) {
                *v = (j * 0.37 + 0.1f64).sin();
                j += 1.0;
            }
        }
        (Params::zeros(n), t)
    }

    fn gradient(p: &Params, t: &Params) -> Params {
        let mut g = p.clone();
        for grp in Group::ALL {
            for (gv, tv) in g.group_mut(grp).iter_mut().zip(t.group(grp)) {
                *gv -= tv;
            }
        }
        g
    }

    #[test]
    fn the_first_step_moves_every_value_by_its_rate_against_the_gradient_sign() {
        let (mut p, t) = bowl(3);
        let mut adam = Adam::new(AdamConfig::default(), 3);
        let g = gradient(&p, &t);
        adam.step(&mut p, &g, [0.1, 0.2, 0.3, 0.4, 0.5]).unwrap();
        for grp in Group::ALL {
            let lr = [0.1, 0.2, 0.3, 0.4, 0.5][grp.index()];
            for (pv, gv) in p.group(grp).iter().zip(g.group(grp)) {
                // Bias-corrected m/√v is exactly ±1 on the first step.
                assert!((pv + lr * gv.signum()).abs() < 1e-9, "{grp:?}");
            }
        }
    }

    #[test]
    fn adam_descends_a_quadratic_bowl() {
        let (mut p, t) = bowl(4);
        let mut adam = Adam::new(AdamConfig::default(), 4);
        for _ in 0..2000 {
            let g = gradient(&p, &t);
            adam.step(&mut p, &g, [0.01; 5]).unwrap();
        }
        assert!(gradient(&p, &t).norm() < 1e-3);
    }

    #[test]
    fn saved_state_resumes_the_same_trajectory() {
        let (mut p, t) = bowl(2);
        let mut adam = Adam::new(AdamConfig::default(), 2);
        for _ in 0..7 {
            let g = gradient(&p, &t);
            adam.step(&mut p, &g, [0.05; 5]).unwrap();
        }
        let path = std::env::temp_dir().join(format!("c4g-adam-{}.json", std::process::id()));
        adam.save(&p, &path).unwrap();
        let (mut adam2, mut p2) = Adam::load(&path).unwrap();
        std::fs::remove_file(&path).unwrap();
        assert_eq!((&adam2, &p2), (&adam, &p));
        for _ in 0..5 {
            let (g, g2) = (gradient(&p, &t), gradient(&p2, &t));
            adam.step(&mut p, &g, [0.05; 5]).unwrap();
            adam2.step(&mut p2, &g2, [0.05; 5]).unwrap();
        }
        assert_eq!(p, p2, "bit for bit");
    }

    #[test]
    fn state_follows_pruning_and_growth_and_refuses_bad_gradients() {
        let (mut p, t) = bowl(3);
        let mut adam = Adam::new(AdamConfig::default(), 3);
        let g = gradient(&p, &t);
        adam.step(&mut p, &g, [0.1; 5]).unwrap();
        adam.select(&[true, false, true]);
        adam.extend(2);
        assert_eq!(adam.len(), 4);
        let mut bad = Params::zeros(4);
        bad.group_mut(Group::Color)[0] = f64::NAN;
        let mut p4 = Params::zeros(4);
        assert!(adam.step(&mut p4, &bad, [0.1; 5]).is_err());
        assert!(adam.step(&mut p, &Params::zeros(3), [0.1; 5]).is_err());
    }
}
