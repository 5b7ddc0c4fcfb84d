//! One training step and the training state (weights, Adam moments, iteration), with exact
//! save/resume. The sample stream is indexed by (seed, index), so the data side resumes by
//! itself: iteration `i` uses samples `i·B .. (i+1)·B`.

use std::collections::HashMap;
use std::path::Path;

use candle_core::{DType, Device, Tensor};
use candle_nn::{VarBuilder, VarMap};
use glam::Vec3;
use ic_data::{Assignment, ObjectSample};

use crate::checkpoint::{self, CONFIG_KEY, STATE_KEY, TrainState};
use crate::config::PoseConfig;
use crate::estimator::PoseEstimator;
use crate::network::{PairBatch, PoseNet, correspondence_accuracy, nearest_assignments, nll_loss};
use crate::{PoseError, Result};
use ic_nn::adam::Adam;
use ic_nn::seeded_var_builder;

/// What one step measured.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct StepStats {
    pub loss: f32,
    /// Arg-max correspondence accuracy over the matched observed points of the batch.
    pub accuracy: Option<f64>,
    /// Matched observed points in the batch.
    pub matched: usize,
}

/// Network + optimiser + position in the run.
pub struct Trainer {
    config: PoseConfig,
    varmap: VarMap,
    net: PoseNet,
    adam: Adam,
    iteration: u64,
    seed: u64,
    device: Device,
}

impl Trainer {
    /// A fresh run: weights drawn from `seed`.
    pub fn new(config: PoseConfig, seed: u64) -> Result<Self> {
        Self::new_on(config, seed, Device::Cpu)
    }

    pub fn new_on(config: PoseConfig, seed: u64, device: Device) -> Result<Self> {
        config.validate()?;
        let varmap = VarMap::new();
        let vb = seeded_var_builder(&varmap, seed, &device);
        let net = PoseNet::new(vb, &config.net)?;
        let adam = Adam::new(&varmap, config.train.learning_rate)?;
        Ok(Trainer {
            config,
            varmap,
            net,
            adam,
            iteration: 0,
            seed,
            device,
        })
    }

    /// Continues the run saved in `path` (configuration, weights, Adam moments, iteration).
    pub fn resume(path: &Path) -> Result<Self> {
        let config = checkpoint::read_config(path)?;
        let state = checkpoint::read_state(path)?;
        let mut t = Self::new(config, state.seed)?;
        ic_nn::checkpoint::restore_training(
            path,
            &t.varmap,
            &mut t.adam,
            state.adam_step,
            &t.device,
        )?;
        t.iteration = state.iteration;
        Ok(t)
    }

    pub fn config(&self) -> &PoseConfig {
        &self.config
    }

    /// Changes the learning rate from the next step on (a step schedule across a resume);
    /// the configuration saved with later checkpoints records the new rate.
    pub fn set_learning_rate(&mut self, learning_rate: f64) {
        self.config.train.learning_rate = learning_rate;
        self.adam.learning_rate = learning_rate;
    }

    /// Changes the planned iteration count (e.g. to extend a resumed run).
    pub fn set_iterations(&mut self, iterations: u64) {
        self.config.train.iterations = iterations;
    }

    pub fn iteration(&self) -> u64 {
        self.iteration
    }

    pub fn seed(&self) -> u64 {
        self.seed
    }

    pub fn device(&self) -> &Device {
        &self.device
    }

    pub fn net(&self) -> &PoseNet {
        &self.net
    }

    pub fn varmap(&self) -> &VarMap {
        &self.varmap
    }

    /// An estimator sharing the current weights (inference mode), e.g. for validation.
    pub fn estimator(&self) -> PoseEstimator {
        PoseEstimator::from_net(self.net.clone(), self.config.clone(), self.device.clone())
    }

    /// Loads the network weights of `path` (weights-only or training checkpoint; its
    /// configuration must equal this trainer's network) without touching Adam or the
    /// iteration count — e.g. to recalibrate batch norm of a shipped model.
    pub fn load_weights(&mut self, path: &Path) -> Result<()> {
        let config = checkpoint::read_config(path)?;
        if config.net != self.config.net {
            return Err(PoseError::Checkpoint {
                path: path.to_path_buf(),
                message: "its network configuration differs from this trainer's".into(),
            });
        }
        let tensors = ic_nn::checkpoint::load_tensors(path, &self.device)?;
        ic_nn::checkpoint::load_into_varmap(&self.varmap, &tensors, path)?;
        Ok(())
    }

    /// Replaces the batch-norm running statistics by their plain mean over `batches`
    /// (forward passes in training mode; the weights do not change) — "precise BN" (Wu &
    /// Johnson, "Rethinking 'Batch' in BatchNorm", 2021). With batch 4 the exponential
    /// average of training (momentum 0.1, a window of ≈ 10 batches) is noisy enough to move
    /// the validation accuracy by tens of points between checkpoints 50 iterations apart.
    pub fn recalibrate_batch_norm(&mut self, batches: &[Vec<ObjectSample>]) -> Result<()> {
        for (k, samples) in batches.iter().enumerate() {
            let mut cfg = self.config.net.clone();
            cfg.bn_momentum = 1.0 / (k + 1) as f64;
            let vb = VarBuilder::from_varmap(&self.varmap, DType::F32, &self.device);
            let net = PoseNet::new(vb, &cfg)?;
            let pairs: Vec<(&[Vec3], &[Vec3])> = samples
                .iter()
                .map(|s| (&s.model_points[..], &s.observed_points[..]))
                .collect();
            let batch = PairBatch::new(&pairs, cfg.k, &self.device)?;
            net.forward_t(&batch, true)?;
        }
        // The trainer's own network shares the variables, so it sees the new statistics.
        Ok(())
    }

    /// One step on ic_data samples. A sample that lists poses equivalent to its true one
    /// (`ObjectSample::alternatives`, a symmetric object) is scored against the equivalent
    /// ground truth nearest the network's prediction ([`nearest_assignments`]), so the loss
    /// never asks for the one turn of a can that its depth cannot show.
    pub fn step(&mut self, samples: &[ObjectSample]) -> Result<StepStats> {
        let pairs: Vec<(&[Vec3], &[Vec3])> = samples
            .iter()
            .map(|s| (&s.model_points[..], &s.observed_points[..]))
            .collect();
        let candidates: Vec<Vec<&Assignment>> = samples
            .iter()
            .map(|s| {
                std::iter::once(&s.assignment)
                    .chain(&s.alternatives)
                    .collect()
            })
            .collect();
        self.step_candidates(&pairs, &candidates)
    }

    /// One step: forward (training mode), loss, backward, Adam.
    pub fn step_pairs(
        &mut self,
        pairs: &[(&[Vec3], &[Vec3])],
        assignments: &[&Assignment],
    ) -> Result<StepStats> {
        let candidates: Vec<Vec<&Assignment>> = assignments.iter().map(|a| vec![*a]).collect();
        self.step_candidates(pairs, &candidates)
    }

    /// One step where each pair's ground truth is the candidate nearest the prediction.
    fn step_candidates(
        &mut self,
        pairs: &[(&[Vec3], &[Vec3])],
        candidates: &[Vec<&Assignment>],
    ) -> Result<StepStats> {
        let batch = PairBatch::new(pairs, self.config.net.k, &self.device)?;
        let out = self.net.forward_t(&batch, true)?;
        let chosen = nearest_assignments(&out, candidates)?;
        let assignments: Vec<&Assignment> =
            candidates.iter().zip(&chosen).map(|(c, k)| c[*k]).collect();
        let assignments = &assignments[..];
        let loss = nll_loss(&out, assignments)?;
        let grads = loss.backward()?;
        self.adam.step(&grads)?;
        let matches = out.matches()?;
        let accuracy = correspondence_accuracy(&matches, assignments);
        self.iteration += 1;
        Ok(StepStats {
            loss: loss.to_scalar::<f32>()?,
            accuracy,
            matched: assignments.iter().map(|a| a.inlier_count()).sum(),
        })
    }

    fn metadata(&self, with_state: bool) -> Result<HashMap<String, String>> {
        let mut meta = HashMap::new();
        let json = |e: serde_json::Error| PoseError::Config(e.to_string());
        meta.insert(
            CONFIG_KEY.to_string(),
            serde_json::to_string(&self.config).map_err(json)?,
        );
        if with_state {
            let state = TrainState {
                iteration: self.iteration,
                seed: self.seed,
                adam_step: self.adam.step_count(),
            };
            meta.insert(
                STATE_KEY.to_string(),
                serde_json::to_string(&state).map_err(json)?,
            );
        }
        Ok(meta)
    }

    fn weights(&self) -> Vec<(String, Tensor)> {
        ic_nn::checkpoint::varmap_tensors(&self.varmap)
    }

    /// Saves everything needed to resume exactly (atomically).
    pub fn save(&self, path: &Path) -> Result<()> {
        let mut tensors = self.weights();
        tensors.extend(self.adam.state());
        checkpoint::save(path, &tensors, self.metadata(true)?)
    }

    /// Saves the weights and configuration only (what inference needs; atomically).
    pub fn save_weights(&self, path: &Path) -> Result<()> {
        checkpoint::save(path, &self.weights(), self.metadata(false)?)
    }
}
