//! Adam (Kingma & Ba, 2015) over a `VarMap`, with its moments exposed for exact resume.
//!
//! candle-nn's `AdamW` keeps its moment estimates private, so a resumed run could not continue
//! to the same numbers; this one saves and restores them. Update (PyTorch's form):
//! `m ← β₁m + (1−β₁)g`, `v ← β₂v + (1−β₂)g²`, `θ ← θ − lr·m̂/(√v̂ + ε)`.

use std::collections::HashMap;

use candle_core::backprop::GradStore;
use candle_core::{Result, Tensor, Var};
use candle_nn::VarMap;

/// Adam over the trainable variables of a `VarMap` (batch-norm running statistics excluded).
pub struct Adam {
    vars: Vec<(String, Var)>,
    m: Vec<Tensor>,
    v: Vec<Tensor>,
    step: u64,
    pub learning_rate: f64,
    pub beta1: f64,
    pub beta2: f64,
    pub eps: f64,
}

/// Whether a variable of the map is trained (running statistics are not).
pub fn is_trainable(name: &str) -> bool {
    !name.contains("running_")
}

impl Adam {
    pub fn new(varmap: &VarMap, learning_rate: f64) -> Result<Self> {
        let mut vars: Vec<(String, Var)> = varmap
            .data()
            .lock()
            .unwrap()
            .iter()
            .filter(|(k, _)| is_trainable(k))
            .map(|(k, v)| (k.clone(), v.clone()))
            .collect();
        vars.sort_by(|a, b| a.0.cmp(&b.0));
        let m = vars
            .iter()
            .map(|(_, v)| v.zeros_like())
            .collect::<Result<Vec<_>>>()?;
        let v = vars
            .iter()
            .map(|(_, v)| v.zeros_like())
            .collect::<Result<Vec<_>>>()?;
        Ok(Adam {
            vars,
            m,
            v,
            step: 0,
            learning_rate,
            beta1: 0.9,
            beta2: 0.999,
            eps: 1e-8,
        })
    }

    pub fn step_count(&self) -> u64 {
        self.step
    }

    /// One update from `grads`; variables without a gradient are left alone.
    pub fn step(&mut self, grads: &GradStore) -> Result<()> {
        self.step += 1;
        let t = self.step as i32;
        let bc1 = 1.0 - self.beta1.powi(t);
        let bc2 = 1.0 - self.beta2.powi(t);
        for (i, (_, var)) in self.vars.iter().enumerate() {
            let Some(g) = grads.get(var.as_tensor()) else {
                continue;
            };
            let cpu_f32 = g.device().is_cpu()
                && [g, &self.m[i], &self.v[i], var.as_tensor()]
                    .iter()
                    .all(|t| t.dtype() == candle_core::DType::F32);
            if cpu_f32 {
                // One pass in plain Rust instead of about ten tensor ops per variable (the same
                // formula, in f32).
                let flat = |t: &Tensor| -> Result<Vec<f32>> { t.flatten_all()?.to_vec1::<f32>() };
                let (gv, mut mv, mut vv, mut theta) = (
                    flat(g)?,
                    flat(&self.m[i])?,
                    flat(&self.v[i])?,
                    flat(var.as_tensor())?,
                );
                let (b1, b2) = (self.beta1 as f32, self.beta2 as f32);
                let (c1, c2) = (bc1 as f32, bc2 as f32);
                let (lr, eps) = (self.learning_rate as f32, self.eps as f32);
                for (((th, m), v), &gi) in theta.iter_mut().zip(&mut mv).zip(&mut vv).zip(&gv) {
                    *m = *m * b1 + gi * (1.0 - b1);
                    *v = *v * b2 + gi * gi * (1.0 - b2);
                    *th -= lr * ((*m / c1) / ((*v / c2).sqrt() + eps));
                }
                let shape = var.shape().clone();
                let dev = g.device();
                var.set(&Tensor::from_vec(theta, shape.clone(), dev)?)?;
                self.m[i] = Tensor::from_vec(mv, shape.clone(), dev)?;
                self.v[i] = Tensor::from_vec(vv, shape, dev)?;
                continue;
            }
            let m = ((&self.m[i] * self.beta1)? + (g * (1.0 - self.beta1))?)?;
            let v = ((&self.v[i] * self.beta2)? + (g.sqr()? * (1.0 - self.beta2))?)?;
            let denom = ((&v / bc2)?.sqrt()? + self.eps)?;
            let update = ((&m / bc1)? / denom)?;
            var.set(&(var.as_tensor().detach() - (update * self.learning_rate)?)?)?;
            self.m[i] = m;
            self.v[i] = v;
        }
        Ok(())
    }

    /// The moments as `adam.m/<var>` and `adam.v/<var>` tensors.
    pub fn state(&self) -> Vec<(String, Tensor)> {
        let mut out = Vec::with_capacity(2 * self.vars.len());
        for (i, (name, _)) in self.vars.iter().enumerate() {
            out.push((format!("adam.m/{name}"), self.m[i].clone()));
            out.push((format!("adam.v/{name}"), self.v[i].clone()));
        }
        out
    }

    /// Restores moments saved by [`Adam::state`] and the step count.
    pub fn load_state(&mut self, tensors: &HashMap<String, Tensor>, step: u64) -> Result<()> {
        for (i, (name, var)) in self.vars.iter().enumerate() {
            for (prefix, slot) in [("adam.m/", &mut self.m[i]), ("adam.v/", &mut self.v[i])] {
                let key = format!("{prefix}{name}");
                let t = tensors
                    .get(&key)
                    .ok_or_else(|| candle_core::Error::Msg(format!("missing {key}")))?;
                if t.shape() != var.shape() {
                    candle_core::bail!("{key}: shape {:?}, expected {:?}", t.shape(), var.shape());
                }
                *slot = t.clone();
            }
        }
        self.step = step;
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use candle_core::{DType, Device};

    #[test]
    fn adam_steps_follow_the_pytorch_formula() {
        let dev = Device::Cpu;
        let varmap = VarMap::new();
        let vb = candle_nn::VarBuilder::from_varmap(&varmap, DType::F32, &dev);
        let x = vb
            .get_with_hints(3, "x", candle_nn::Init::Const(1.0))
            .unwrap();
        let mut adam = Adam::new(&varmap, 0.1).unwrap();
        // loss = Σ c_i x_i²  →  g = 2 c_i x_i.
        let c = Tensor::new(&[0.5f32, -1.0, 2.0], &dev).unwrap();
        let (mut theta, mut m, mut v) = ([1.0f64; 3], [0.0f64; 3], [0.0f64; 3]);
        let cv = [0.5f64, -1.0, 2.0];
        for t in 1..=3 {
            let loss = (x.sqr().unwrap() * &c).unwrap().sum_all().unwrap();
            adam.step(&loss.backward().unwrap()).unwrap();
            for i in 0..3 {
                let g = 2.0 * cv[i] * theta[i];
                m[i] = 0.9 * m[i] + 0.1 * g;
                v[i] = 0.999 * v[i] + 0.001 * g * g;
                let mh = m[i] / (1.0 - 0.9f64.powi(t));
                let vh = v[i] / (1.0 - 0.999f64.powi(t));
                theta[i] -= 0.1 * mh / (vh.sqrt() + 1e-8);
            }
            let got = x.to_vec1::<f32>().unwrap();
            for i in 0..3 {
                assert!(
                    (got[i] as f64 - theta[i]).abs() < 1e-5,
                    "step {t}: {got:?} vs {theta:?}"
                );
            }
        }
        assert_eq!(adam.step_count(), 3);
    }
}
