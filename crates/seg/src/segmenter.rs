//! The inference API: [`Segmenter::load`] then [`Segmenter::segment`].

use std::path::Path;
use std::time::Instant;

use candle_core::{DType, Device, Tensor};
use candle_nn::VarBuilder;
use glam::Vec3;
use ic_geometry::{DepthImage, Image, Intrinsics, Mask};

use crate::centres::CentreVotes;
use crate::config::{SegConfig, SegInput};
use crate::infer::FoldedUNet;
use crate::input::{mirror_planes, prepare_input, upsample_bilinear};
use crate::post::{Instance, best_instance, erode3x3, instances, masked_points, split_instances};
use crate::unet::UNet;
use crate::{Result, SegError, checkpoint};

/// The camera every network here is trained through (resized to the network's input): the
/// scene generators' Kinect-like 640×480 one, fx = fy = 525 pixels.
pub const TRAINING_CAMERA: Intrinsics = Intrinsics::KINECT_640X480;

/// The object found in a depth map.
#[derive(Clone, Debug, PartialEq)]
pub struct Segmentation {
    /// The best instance's pixels at the depth map's resolution (snapped to depth edges when
    /// `post.depth_refine_px` > 0; before erosion).
    pub mask: Mask,
    /// Its score: the mean object probability over its pixels, in [0, 1].
    pub score: f32,
    /// The object probability of every pixel, at the depth map's resolution.
    pub probability: Image<f32>,
    /// Seconds spent in the network (input preparation included) and in post-processing.
    pub network_seconds: f64,
    pub post_seconds: f64,
}

/// A trained instance-mask network with its post-processing settings.
#[derive(Clone, Debug)]
pub struct Segmenter {
    net: UNet,
    config: SegConfig,
    device: Device,
}

impl Segmenter {
    /// Loads a checkpoint written by `cargo xtask train-seg` (the configuration is read from
    /// its metadata).
    ///
    /// Errors: missing or unreadable file, not an `ic_seg` checkpoint, weights that do not
    /// fit the recorded network.
    pub fn load(path: &Path) -> Result<Segmenter> {
        let config = checkpoint::read_config(path)?;
        let device = Device::Cpu;
        let tensors =
            candle_core::safetensors::load(path, &device).map_err(|e| SegError::Checkpoint {
                path: path.to_path_buf(),
                message: format!("reading the weights: {e}"),
            })?;
        let vb = VarBuilder::from_tensors(tensors, DType::F32, &device);
        let net = UNet::new(vb, &config.net).map_err(|e| SegError::Checkpoint {
            path: path.to_path_buf(),
            message: format!("the weights do not fit the network in its metadata: {e}"),
        })?;
        Ok(Segmenter {
            net,
            config,
            device,
        })
    }

    /// Wraps an in-memory network (e.g. the trainer's).
    pub fn from_parts(net: UNet, config: SegConfig) -> Segmenter {
        Segmenter {
            net,
            config,
            device: Device::Cpu,
        }
    }

    pub fn config(&self) -> &SegConfig {
        &self.config
    }

    /// The network's input size (pixels) for the images of camera `k` when
    /// [`crate::PostConfig::camera_input`] is on: each side is the image's side × the
    /// network's focal length / the camera's (fx for the width, fy for the height), so that a
    /// network pixel spans the angle it spanned in training — every network here is trained
    /// on scenes seen through [`TRAINING_CAMERA`] resized to the input, 525 pixels of focal
    /// length at 640×480 — and the aspect ratio is the image's. Then, both sides together,
    /// brought under 4× the trained input's area (the time and memory of the network grow
    /// with it) and over 4 levels' worth of pixels on the short side, and each rounded to
    /// the network's multiple. The training camera itself gives `input_width ×
    /// input_height` exactly; with the option off, always that.
    pub fn input_size_for(&self, k: &Intrinsics) -> (u32, u32) {
        let net = &self.config.net;
        if !self.config.post.camera_input {
            return (net.input_width, net.input_height);
        }
        let div = 1u32 << (net.channels.len() - 1);
        let t = TRAINING_CAMERA;
        // The network's focal lengths, in network pixels.
        let fx = t.fx * net.input_width as f64 / t.width as f64;
        let fy = t.fy * net.input_height as f64 / t.height as f64;
        let (mut w, mut h) = (k.width as f64 * fx / k.fx, k.height as f64 * fy / k.fy);
        let cap = 4.0 * net.input_width as f64 * net.input_height as f64;
        if w * h > cap {
            let s = (cap / (w * h)).sqrt();
            (w, h) = (w * s, h * s);
        }
        let short = (4 * div) as f64;
        if w.min(h) < short {
            let s = short / w.min(h);
            (w, h) = (w * s, h * s);
        }
        let side = |v: f64| {
            ((v / div as f64).round().max(1.0) as u32 * div)
                .min(crate::config::MAX_INPUT_SIDE / div * div)
        };
        (side(w), side(h))
    }

    /// This segmenter with its input sized for camera `k` ([`Segmenter::input_size_for`];
    /// the weights are shared), to run and post-process images of that camera.
    pub fn for_camera(&self, k: &Intrinsics) -> Segmenter {
        let (w, h) = self.input_size_for(k);
        let mut s = self.clone();
        s.config.net.input_width = w;
        s.config.net.input_height = h;
        // Sized once: the sized network's own input is not the trained one's.
        s.config.post.camera_input = false;
        s
    }

    /// Settings of the post-processing, e.g. to lower the score threshold.
    pub fn config_mut(&mut self) -> &mut SegConfig {
        &mut self.config
    }

    /// Per-pixel probabilities of `images` (each a depth map and its camera) at the network's
    /// resolution, `[B][outputs·H·W]` (the object map, then the core map of a two- or
    /// four-output network, then a four-output network's centre offsets x and y as they are,
    /// in [`crate::config::OFFSET_UNIT`]s of network pixels). With
    /// [`crate::PostConfig::mirror_average`], the mean of the pass on each image and the pass
    /// on its mirror image (mirrored back, the x offsets negated).
    pub fn probabilities_small(
        &self,
        images: &[(&DepthImage, &Intrinsics)],
    ) -> Result<Vec<Vec<f32>>> {
        let (w, h) = (self.config.net.input_width, self.config.net.input_height);
        let kind = self.config.net.input;
        let mut inputs = images
            .iter()
            .map(|(d, k)| prepare_input(d, k, kind, w, h))
            .collect::<Result<Vec<_>>>()?;
        if !self.config.post.mirror_average {
            return self.outputs_small(&inputs);
        }
        // One pass over the images and their mirror images together (the network is folded
        // once); the normal's x component (input channel 2) changes sign in a mirror image.
        let (n, (w, h)) = (inputs.len(), (w as usize, h as usize));
        let normal_x = (kind == SegInput::DepthNormals).then_some(2);
        let mirrored: Vec<Vec<f32>> = inputs
            .iter()
            .map(|x| {
                let mut x = x.clone();
                mirror_planes(&mut x, w, h, normal_x);
                x
            })
            .collect();
        inputs.extend(mirrored);
        let mut out = self.outputs_small(&inputs)?;
        let back = out.split_off(n);
        // The mirrored passes mirrored back, their x offsets (output plane 2) negated.
        let offset_x = self.config.net.has_offsets().then_some(2);
        for (o, mut m) in out.iter_mut().zip(back) {
            mirror_planes(&mut m, w, h, offset_x);
            o.iter_mut().zip(&m).for_each(|(a, b)| *a = 0.5 * (*a + b));
        }
        Ok(out)
    }

    /// One pass of the network on prepared inputs (each `[C·H·W]`): the probability maps
    /// through the sigmoid, the centre offsets as they are.
    fn outputs_small(&self, inputs: &[Vec<f32>]) -> Result<Vec<Vec<f32>>> {
        let (w, h) = (self.config.net.input_width, self.config.net.input_height);
        let kind = self.config.net.input;
        // The probability maps (object, core); the centre offsets stay as they are.
        let maps = self.config.net.outputs.min(2);
        let plane = (w * h) as usize;
        if self.device.is_cpu() {
            // The folded network (batch norm in the convolutions, no tensor ops): the same
            // function, several times faster on the CPU. Folded per call, so a segmenter
            // sharing a network in training sees its current weights.
            let folded = FoldedUNet::new(&self.net)?;
            return inputs
                .iter()
                .map(|input| {
                    let mut logits = folded.forward(input, h as usize, w as usize)?;
                    logits[..maps * plane]
                        .iter_mut()
                        .for_each(|v| *v = 1.0 / (1.0 + (-*v).exp()));
                    Ok(logits)
                })
                .collect();
        }
        let x = Tensor::from_vec(
            inputs.concat(),
            (inputs.len(), kind.channels(), h as usize, w as usize),
            &self.device,
        )?;
        let logits = self.net.forward_t(&x, false)?.detach();
        let mut p = candle_nn::ops::sigmoid(&logits.narrow(1, 0, maps)?)?;
        let rest = logits.dim(1)? - maps;
        if rest > 0 {
            p = Tensor::cat(&[&p, &logits.narrow(1, maps, rest)?], 1)?;
        }
        Ok(p.flatten_from(1)?.to_vec2::<f32>()?)
    }

    /// Output map `index` of `small` (one image of [`Segmenter::probabilities_small`])
    /// up-sampled to `depth`'s resolution, 0 where the sensor saw nothing.
    fn full_resolution(&self, small: &[f32], index: usize, depth: &DepthImage) -> Vec<f32> {
        let (w, h) = (self.config.net.input_width, self.config.net.input_height);
        let plane = (w * h) as usize;
        let mut prob = upsample_bilinear(
            &small[index * plane..(index + 1) * plane],
            w,
            h,
            depth.width,
            depth.height,
        );
        for (p, z) in prob.iter_mut().zip(&depth.data) {
            if !(z.is_finite() && *z > 0.0) {
                *p = 0.0;
            }
        }
        prob
    }

    /// Finds the object in `depth` (any resolution; it must match `intrinsics`).
    ///
    /// Errors: [`SegError::ObjectNotFound`] when no instance scores above the threshold;
    /// [`SegError::Input`] / geometry errors for a depth map that does not fit the camera or
    /// has no valid pixel.
    pub fn segment(&self, depth: &DepthImage, intrinsics: &Intrinsics) -> Result<Segmentation> {
        intrinsics.check_image(depth)?;
        if self.config.post.camera_input {
            return self.for_camera(intrinsics).segment(depth, intrinsics);
        }
        let t0 = Instant::now();
        let small = self.probabilities_small(&[(depth, intrinsics)])?.remove(0);
        let network_seconds = t0.elapsed().as_secs_f64();
        let t1 = Instant::now();
        let prob = self.full_resolution(&small, 0, depth);
        let post = &self.config.post;
        let best = best_instance(
            &prob,
            depth.width,
            depth.height,
            post.pixel_threshold,
            post.score_threshold,
            post.min_pixels_at(depth.width, depth.height),
        )?;
        let mask = post.refine(best.mask, depth);
        Ok(Segmentation {
            mask,
            score: best.score,
            probability: Image {
                width: depth.width,
                height: depth.height,
                data: prob,
            },
            network_seconds,
            post_seconds: t1.elapsed().as_secs_f64(),
        })
    }

    /// The centre votes of `small` (one image of [`Segmenter::probabilities_small`]) at
    /// `depth`'s resolution; `None` without centre offsets.
    fn votes_from(&self, small: &[f32], depth: &DepthImage) -> Option<CentreVotes> {
        let net = &self.config.net;
        if !net.has_offsets() {
            return None;
        }
        let unit = crate::config::OFFSET_UNIT;
        Some(CentreVotes::from_offsets(
            &self.full_resolution(small, 2, depth),
            &self.full_resolution(small, 3, depth),
            depth.width,
            unit * depth.width as f32 / net.input_width as f32,
            unit * depth.height as f32 / net.input_height as f32,
            depth.width as f32 / net.input_width as f32,
        ))
    }

    /// Every object instance in `depth` (any resolution; it must match `intrinsics`), best
    /// score first, masks at the depth map's resolution. A one-output network's instances
    /// are the connected components of its object map; a two-output network's are split by
    /// their cores ([`split_instances`], growth stopped at relative depth steps above
    /// `post.depth_jump`); a four-output network's cores are also cut and joined by their
    /// centre votes when `post.centres` says so ([`crate::centres`]). Instances below `post.min_pixels` (given for 640×480, scaled with
    /// the area) are dropped; none is an empty list, not an error.
    pub fn instances(&self, depth: &DepthImage, intrinsics: &Intrinsics) -> Result<Vec<Instance>> {
        Ok(self.instances_inner(depth, intrinsics, false)?.0)
    }

    /// [`Segmenter::instances`] at the network's own input size, then at each size of
    /// `post.extra_inputs` in its order: one list per input size, each a partition of its
    /// own (instances of different sizes overlap). The same weights run at every size (the
    /// network is fully convolutional); the post-processing settings are shared.
    ///
    /// Errors: as [`Segmenter::instances`].
    pub fn instances_per_input(
        &self,
        depth: &DepthImage,
        intrinsics: &Intrinsics,
    ) -> Result<Vec<Vec<Instance>>> {
        let mut out = vec![self.instances(depth, intrinsics)?];
        for &(width, height) in &self.config.post.extra_inputs {
            out.push(self.at_input(width, height).instances(depth, intrinsics)?);
        }
        Ok(out)
    }

    /// This segmenter with the network's input size `width × height` (pixels) whatever the
    /// camera, and no extra input sizes (the weights are shared, not copied).
    pub fn at_input(&self, width: u32, height: u32) -> Segmenter {
        let mut s = self.clone();
        s.config.net.input_width = width;
        s.config.net.input_height = height;
        s.config.post.extra_inputs.clear();
        s.config.post.camera_input = false;
        s
    }

    /// [`Segmenter::instances`] and, from the same pass of the network, a four-output
    /// network's centre votes (where each pixel says its instance's centre is, in pixels of
    /// `depth`; `None` without centre offsets), whether or not `post.centres` uses them.
    pub fn instances_and_votes(
        &self,
        depth: &DepthImage,
        intrinsics: &Intrinsics,
    ) -> Result<(Vec<Instance>, Option<CentreVotes>)> {
        self.instances_inner(depth, intrinsics, true)
    }

    /// The instances, and the votes when `want_votes` or `post.centres` needs them.
    fn instances_inner(
        &self,
        depth: &DepthImage,
        intrinsics: &Intrinsics,
        want_votes: bool,
    ) -> Result<(Vec<Instance>, Option<CentreVotes>)> {
        intrinsics.check_image(depth)?;
        if self.config.post.camera_input {
            return self
                .for_camera(intrinsics)
                .instances_inner(depth, intrinsics, want_votes);
        }
        let small = self.probabilities_small(&[(depth, intrinsics)])?.remove(0);
        self.post_process(&small, depth, intrinsics, want_votes)
    }

    /// The post-processing of [`Segmenter::instances_and_votes`] applied to given outputs
    /// `small` at the network's resolution, laid out as one image of
    /// [`Segmenter::probabilities_small`] (probabilities, then offsets in
    /// [`crate::config::OFFSET_UNIT`]s). `eval-seg --oracle` passes the training targets here
    /// to measure what the representation and its post-processing allow with a perfect
    /// network. Votes come back when `want_votes` or `post.centres` needs them.
    ///
    /// Errors: `small` not `outputs × H × W` of the configuration; a depth map that does not
    /// fit the camera.
    pub fn instances_from_small(
        &self,
        small: &[f32],
        depth: &DepthImage,
        intrinsics: &Intrinsics,
        want_votes: bool,
    ) -> Result<(Vec<Instance>, Option<CentreVotes>)> {
        intrinsics.check_image(depth)?;
        let net = &self.config.net;
        let expected = net.outputs * (net.input_width * net.input_height) as usize;
        if small.len() != expected {
            return Err(SegError::Input(format!(
                "{} network outputs, expected {} ({} maps of {}×{})",
                small.len(),
                expected,
                net.outputs,
                net.input_width,
                net.input_height
            )));
        }
        self.post_process(small, depth, intrinsics, want_votes)
    }

    /// The post-processing of checked outputs `small` (see
    /// [`Segmenter::instances_from_small`]).
    fn post_process(
        &self,
        small: &[f32],
        depth: &DepthImage,
        intrinsics: &Intrinsics,
        want_votes: bool,
    ) -> Result<(Vec<Instance>, Option<CentreVotes>)> {
        let object = self.full_resolution(small, 0, depth);
        let post = &self.config.post;
        let min_pixels = post.min_pixels_at(depth.width, depth.height);
        let votes = if want_votes || post.centres.is_some() {
            self.votes_from(small, depth)
        } else {
            None
        };
        let mut found = if self.config.net.has_core() {
            let core = self.full_resolution(small, 1, depth);
            split_instances(
                &object,
                &core,
                depth.width,
                depth.height,
                post.pixel_threshold,
                post.core_threshold,
                min_pixels,
                Some((depth, post.depth_jump)),
                votes.as_ref().zip(post.centres.as_ref()),
            )
        } else {
            instances(
                &object,
                depth.width,
                depth.height,
                post.pixel_threshold,
                min_pixels,
            )
        };
        if let Some(cfg) = &post.support {
            let planes = crate::support::support_planes(depth, intrinsics, cfg);
            if !planes.is_empty() {
                let mut free = crate::support::off_planes(depth, intrinsics, &planes, cfg);
                let mut label = vec![u32::MAX; free.len()];
                for (k, inst) in found.iter().enumerate() {
                    for (i, &m) in inst.mask.data.iter().enumerate() {
                        if m {
                            label[i] = k as u32;
                            free[i] = false;
                        }
                    }
                }
                if cfg.grow {
                    crate::support::grow_into(&mut label, &mut free, depth, post.depth_jump);
                    for (i, &l) in label.iter().enumerate() {
                        if l != u32::MAX && !found[l as usize].mask.data[i] {
                            found[l as usize].mask.data[i] = true;
                            found[l as usize].pixels += 1;
                        }
                    }
                }
                let groups = crate::support::free_groups(&free, depth, post.depth_jump, min_pixels);
                found.extend(
                    crate::post::ranked(groups, &object, depth.width, depth.height, min_pixels)
                        .into_iter()
                        .map(|i| crate::post::Instance {
                            off_support: true,
                            ..i
                        }),
                );
            }
        }
        Ok((found, votes))
    }

    /// The observed object points of a segmentation, as the paper prepares them: the mask
    /// eroded (`post.erosions` times 3×3), back-projected, and cropped to `crop_radius ×
    /// object_scale` around the masked points' centre. `object_scale` is the model's
    /// normalisation scale in the depth map's units (1 for normalised units).
    pub fn object_points(
        &self,
        depth: &DepthImage,
        intrinsics: &Intrinsics,
        segmentation: &Segmentation,
        object_scale: f64,
    ) -> Result<Vec<Vec3>> {
        let mut mask = segmentation.mask.clone();
        for _ in 0..self.config.post.erosions {
            let eroded = erode3x3(&mask);
            if !eroded.data.iter().any(|&m| m) {
                break; // a sliver: keep what there is rather than nothing
            }
            mask = eroded;
        }
        masked_points(
            depth,
            intrinsics,
            &mask,
            self.config.post.crop_radius * object_scale,
        )
    }
}
