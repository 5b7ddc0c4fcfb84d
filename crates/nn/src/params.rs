//! Seeded parameter initialisation: a `VarBuilder` backend over a [`VarMap`] whose random
//! initialisers draw from a ChaCha8 generator, so the same seed gives the same network
//! (candle's own CPU initialisers use an unseeded thread RNG).

use std::sync::Mutex;

use candle_core::{DType, Device, Result, Shape, Tensor, Var};
use candle_nn::var_builder::SimpleBackend;
use candle_nn::{Init, VarBuilder, VarMap};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

struct Seeded {
    map: VarMap,
    rng: Mutex<ChaCha8Rng>,
}

impl SimpleBackend for Seeded {
    fn get(&self, s: Shape, name: &str, h: Init, dtype: DType, dev: &Device) -> Result<Tensor> {
        let mut data = self.map.data().lock().unwrap();
        if let Some(v) = data.get(name) {
            if v.shape() != &s {
                candle_core::bail!("{name}: shape {:?} vs requested {s:?}", v.shape());
            }
            return Ok(v.as_tensor().clone());
        }
        let n = s.elem_count();
        let values: Vec<f32> = match h {
            Init::Const(c) => vec![c as f32; n],
            Init::Uniform { lo, up } => {
                let mut rng = self.rng.lock().unwrap();
                (0..n).map(|_| rng.random_range(lo..up) as f32).collect()
            }
            other => candle_core::bail!("{name}: unsupported initialiser {other:?}"),
        };
        let t = Tensor::from_vec(values, s, dev)?.to_dtype(dtype)?;
        let var = Var::from_tensor(&t)?;
        let t = var.as_tensor().clone();
        data.insert(name.to_string(), var);
        Ok(t)
    }

    fn get_unchecked(&self, name: &str, _dtype: DType, _dev: &Device) -> Result<Tensor> {
        candle_core::bail!("{name}: get_unchecked is not supported by the seeded VarMap")
    }

    fn contains_tensor(&self, name: &str) -> bool {
        self.map.data().lock().unwrap().contains_key(name)
    }
}

/// A `VarBuilder` that creates (or reuses) the variables of `map`, drawing random initial
/// values from a generator seeded with `seed`. Build order is deterministic, so the values are.
pub fn seeded_var_builder(map: &VarMap, seed: u64, device: &Device) -> VarBuilder<'static> {
    let backend: Box<dyn SimpleBackend> = Box::new(Seeded {
        map: map.clone(),
        rng: Mutex::new(ChaCha8Rng::seed_from_u64(seed)),
    });
    VarBuilder::from_backend(backend, DType::F32, device.clone())
}
