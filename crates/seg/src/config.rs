//! Serde configurations with named presets (`cpu`, `clutter`, `clutter-wide`,
//! `clutter-offsets…`, `tiny…`).

use serde::{Deserialize, Serialize};

use crate::{Result, SegError};

/// The encoder–decoder.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct UNetConfig {
    /// The network's input size; any depth map is resized to it (nearest neighbour, so no
    /// depth is invented across edges). Both must be divisible by 2^(levels − 1).
    pub input_width: u32,
    pub input_height: u32,
    /// Channels per level, finest first; each level after the first halves the resolution.
    pub channels: Vec<usize>,
    /// Batch-norm momentum of the running statistics.
    pub bn_momentum: f64,
    /// Output maps: 1 = object probability (the paper's); 2 = object probability and
    /// instance **core** (an object's pixels at least `train.core_radius` pixels inside its
    /// own outline), whose connected components separate touching instances; 4 = those two
    /// and the **centre offset** (x, then y): from each object pixel to the centroid of its
    /// instance's visible pixels, in units of [`OFFSET_UNIT`] network pixels (image axes: x
    /// right, y down), so that a core joining two objects can be cut where its pixels point
    /// to two centres ([`crate::post::split_instances`]).
    #[serde(default = "one")]
    pub outputs: usize,
    /// What the network sees of the depth map ([`crate::input`]); checkpoints written before
    /// the choice existed read as [`SegInput::Depth`].
    #[serde(default)]
    pub input: SegInput,
    /// Four-output networks: 0 (the default), the centre offsets come from the head on the
    /// finest level like the maps; `l` ≥ 1, a dedicated branch also reads the features of
    /// level `l` (decoder output, or the bottleneck for the coarsest level: `channels[l]`
    /// channels at 1/2^l of the input), one 3×3 convolution + batch norm + ReLU and a 1×1
    /// convolution to (x, y), up-sampled (nearest) to the input's size and added to the head's
    /// offsets. Where whole objects are a few pixels the branch sees each object's extent
    /// at once; the finest head corrects its blocks.
    #[serde(default, skip_serializing_if = "is_zero")]
    pub offset_level: usize,
}

fn is_zero(v: &usize) -> bool {
    *v == 0
}

/// The network's input channels.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum SegInput {
    /// The depth divided by its median, minus one, and a validity flag (2 channels).
    #[default]
    Depth,
    /// Those two and the unit surface normal of each pixel (camera frame: x right, y down,
    /// z forward; turned towards the camera), 5 channels: local orientation, so that the
    /// crease where two objects touch, or where an object meets the table, is explicit.
    DepthNormals,
}

impl SegInput {
    /// Input channels of the network.
    pub fn channels(self) -> usize {
        match self {
            SegInput::Depth => 2,
            SegInput::DepthNormals => 5,
        }
    }
}

impl std::str::FromStr for SegInput {
    type Err = SegError;

    fn from_str(s: &str) -> Result<Self> {
        match s {
            "depth" => Ok(SegInput::Depth),
            "depth-normals" | "depth_normals" => Ok(SegInput::DepthNormals),
            other => Err(SegError::Config(format!(
                "unknown input {other:?}: expected depth or depth-normals"
            ))),
        }
    }
}

fn one() -> usize {
    1
}

/// The centre-offset maps' unit, in network pixels: a target of 1 is 16 pixels of the
/// network's input (e.g. 40 pixels of a 640-pixel-wide depth map seen at 256). Chosen so the
/// offsets of the objects the clutter scenes hold (≈ 5–100 network pixels across) are of the
/// order of one, as the other outputs' logits are.
pub const OFFSET_UNIT: f32 = 16.0;

impl UNetConfig {
    /// Whether the network has the instance-core map (output 1).
    pub fn has_core(&self) -> bool {
        self.outputs >= 2
    }

    /// Whether the network has the centre-offset maps (outputs 2 and 3, see [`OFFSET_UNIT`]).
    pub fn has_offsets(&self) -> bool {
        self.outputs == 4
    }

    /// Checks an input size `width × height` (pixels) the network may run at: positive, each
    /// side divisible by 2^(levels − 1) and at most [`MAX_INPUT_SIDE`]; `what` names it in
    /// the error ("input", "extra input"). The channels must be checked first.
    pub fn check_input(&self, what: &str, width: u32, height: u32) -> Result<()> {
        let div = 1u32 << (self.channels.len() - 1);
        if width == 0
            || height == 0
            || width % div != 0
            || height % div != 0
            || width.max(height) > MAX_INPUT_SIDE
        {
            return Err(SegError::Config(format!(
                "{what} {width}×{height} must be positive, divisible by {div} for {} levels and at most {MAX_INPUT_SIDE} a side",
                self.channels.len()
            )));
        }
        Ok(())
    }

    pub fn validate(&self) -> Result<()> {
        let bad = |m: String| Err(SegError::Config(m));
        if self.channels.is_empty() || self.channels.contains(&0) {
            return bad("channels must be non-empty and positive".into());
        }
        self.check_input("input", self.input_width, self.input_height)?;
        if ![1, 2, 4].contains(&self.outputs) {
            return bad(format!(
                "outputs {} must be 1 (object), 2 (and core) or 4 (and centre offsets)",
                self.outputs
            ));
        }
        if self.offset_level > 0 && (self.outputs != 4 || self.offset_level >= self.channels.len())
        {
            return bad(format!(
                "offset_level {} needs a four-output network (this one has {}) and a level below {}",
                self.offset_level,
                self.outputs,
                self.channels.len()
            ));
        }
        if !(self.bn_momentum > 0.0 && self.bn_momentum <= 1.0) {
            return bad(format!(
                "bn_momentum {} must be in (0, 1]",
                self.bn_momentum
            ));
        }
        Ok(())
    }
}

/// The paper's post-processing (Sec. 3.1): threshold, connected components, best instance,
/// 3×3 erosion, back-projection, crop around the masked points' centre.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct PostConfig {
    /// Pixel probability above which a pixel is foreground. 0.3 rather than 0.5: the depth
    /// refinement removes what spills over a depth edge, so the mask may start generous
    /// (chosen on validation scenes, see `models/README.md`).
    pub pixel_threshold: f32,
    /// An instance's score (the mean probability over its pixels) must exceed this.
    pub score_threshold: f32,
    /// Components smaller than this (pixels, at the depth map's own resolution) are ignored.
    pub min_pixels: usize,
    /// Snap the up-sampled mask to depth edges within this many pixels of its boundary
    /// (given for 640 pixels of width, scaled with the image; 0 = off). Not in the paper: its
    /// YOLACT masks are predicted at a higher resolution than our 160×120 network sees.
    #[serde(default = "default_depth_refine_px")]
    pub depth_refine_px: usize,
    /// Largest relative depth step between neighbouring pixels of one surface, for the
    /// refinement.
    #[serde(default = "default_depth_jump")]
    pub depth_jump: f32,
    /// 3×3 erosions applied before back-projection (the paper: 1).
    pub erosions: usize,
    /// Points farther than this from the masked points' centre are dropped, in normalised
    /// object units (multiplied by the model's normalisation scale; the paper: 1.2).
    pub crop_radius: f64,
    /// Two-output networks: core probability above which a pixel seeds an instance.
    #[serde(default = "default_core_threshold")]
    pub core_threshold: f32,
    /// [`crate::Segmenter::instances`] adds the pixel groups off the scene's support planes
    /// that no network instance holds ([`crate::support`]); `None`: off.
    #[serde(default)]
    pub support: Option<crate::SupportConfig>,
    /// Four-output networks: how the centre votes cut and join the cores' instances
    /// ([`crate::centres`]); `None`: the offsets are not used.
    #[serde(default)]
    pub centres: Option<crate::centres::CentreConfig>,
    /// Test-time mirroring: the network also sees the depth map mirrored left to right, and
    /// its outputs are the mean of the two passes (the mirrored pass mirrored back, its x
    /// centre offsets negated). Twice the network's time; the training is unchanged (a scene
    /// and its mirror image are equally likely: objects fall at random, gravity stays down).
    #[serde(default)]
    pub mirror_average: bool,
    /// More input sizes `(width, height)` (pixels) the network also runs at, besides its own
    /// `input_width × input_height`: [`crate::Segmenter::instances_per_input`] gives each
    /// size's instances, each size's set a partition of its own, for a pipeline that pools
    /// them as candidates (a finer input cuts apart touching objects that the training size
    /// joins; a coarser one keeps whole what it cuts), whatever the camera. Empty (the
    /// default): the network's own size alone. At most [`MAX_EXTRA_INPUTS`], each side at most [`MAX_INPUT_SIDE`] and
    /// divisible like the network's own.
    #[serde(default)]
    pub extra_inputs: Vec<(u32, u32)>,
    /// Size the network's input for each image's camera
    /// ([`crate::Segmenter::input_size_for`]): a network pixel spans the angle it spanned in
    /// training and the image keeps its aspect ratio, so the objects of a 16:9, wide-angle or
    /// high-resolution camera reach the network at the shape and size it learned. `false`:
    /// always `input_width × input_height` (another aspect ratio squeezed into it). Files
    /// written before the field: on.
    #[serde(default = "default_camera_input")]
    pub camera_input: bool,
}

fn default_camera_input() -> bool {
    true
}

/// The most extra input sizes [`PostConfig::extra_inputs`] may list (each costs a pass of
/// the network).
pub const MAX_EXTRA_INPUTS: usize = 4;

/// The longest side, in pixels, of the network's input, its own or an extra size (at
/// 2048×2048 one 16-channel feature map of the first level holds 256 MiB): a checkpoint
/// asking for more is refused rather than allowed to take the machine's memory.
pub const MAX_INPUT_SIDE: u32 = 2048;

fn default_core_threshold() -> f32 {
    0.5
}

fn default_depth_refine_px() -> usize {
    4
}

fn default_depth_jump() -> f32 {
    0.03
}

impl PostConfig {
    /// Turns the support instances on at `height` (relative to the depth; 0: off), keeping
    /// the other support settings (the defaults when off before) and setting the plane
    /// threshold and the growth of the network's instances when given.
    pub fn set_support(&mut self, height: f32, plane_threshold: Option<f32>, grow: Option<bool>) {
        let base = self.support.clone().unwrap_or_default();
        self.support = (height != 0.0).then(|| crate::SupportConfig {
            height,
            plane_threshold: plane_threshold.unwrap_or(base.plane_threshold),
            grow: grow.unwrap_or(base.grow),
            ..base
        });
    }

    /// `min_pixels` (given for a 640×480 map) scaled to a `width`×`height` map's area.
    pub fn min_pixels_at(&self, width: u32, height: u32) -> usize {
        let area = (width as f64 * height as f64) / (640.0 * 480.0);
        ((self.min_pixels as f64 * area).round() as usize).max(1)
    }

    /// `mask` snapped to the depth edges of `depth` within `depth_refine_px` (given for 640
    /// pixels of width, scaled with the map's width); `mask` itself when the refinement is
    /// off.
    pub fn refine(
        &self,
        mask: ic_geometry::Mask,
        depth: &ic_geometry::DepthImage,
    ) -> ic_geometry::Mask {
        if self.depth_refine_px == 0 {
            return mask;
        }
        let band =
            ((self.depth_refine_px as f64 * depth.width as f64 / 640.0).round() as usize).max(1);
        crate::post::refine_with_depth(&mask, depth, band, self.depth_jump)
    }
}

impl Default for PostConfig {
    fn default() -> Self {
        PostConfig {
            pixel_threshold: 0.3,
            score_threshold: 0.5,
            min_pixels: 30,
            depth_refine_px: 4,
            depth_jump: 0.03,
            erosions: 1,
            crop_radius: 1.2,
            core_threshold: 0.5,
            support: None,
            centres: None,
            mirror_average: false,
            extra_inputs: Vec::new(),
            camera_input: true,
        }
    }
}

/// Training settings.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SegTrainConfig {
    pub batch_size: usize,
    pub learning_rate: f64,
    pub iterations: u64,
    /// Weight of the soft-Dice term beside the per-pixel binary cross-entropy.
    pub dice_weight: f64,
    /// Training scenes are rendered at this size (field of view kept) and then resized to
    /// the network input like any depth map.
    pub render_width: u32,
    pub render_height: u32,
    /// Two-output networks: the instance core is an object's pixels whose neighbours within
    /// this many pixels (square, at the network's resolution) all show the same object.
    #[serde(default = "default_core_radius")]
    pub core_radius: usize,
    /// Four-output networks: weight of the centre offsets' loss (the mean absolute error
    /// over the object pixels, in [`OFFSET_UNIT`]s, both axes) beside the maps' cross-entropy
    /// and Dice terms.
    #[serde(default = "default_offset_weight")]
    pub offset_weight: f64,
    /// Instance balance (clutter scenes; 0: off): the object pixels of an instance of `n`
    /// network pixels weigh `clamp(√(balance_area / n), 1, BALANCE_CAP)` in the
    /// cross-entropy and the offsets' error, every other pixel 1. The target found rate
    /// counts a small target as much as a large one; the unweighted per-pixel loss counts it
    /// by its pixels. Written only when on, so files without it stay readable by older
    /// builds.
    #[serde(default, skip_serializing_if = "is_zero_f64")]
    pub balance_area: f64,
    /// Contact weight (clutter scenes; 0: off; the "separation border" weight of the U-Net
    /// paper, Ronneberger et al. 2015): an object pixel at `d` network pixels from another
    /// object instance weighs `1 + border_weight · exp(−d² / (2 · BORDER_SIGMA²))` (times the
    /// balance weight) in the cross-entropy, so the thin non-core band where two objects
    /// touch — what parts them — counts. Written only when on.
    #[serde(default, skip_serializing_if = "is_zero_f64")]
    pub border_weight: f64,
    /// Clutter scenes: the probability that a training scene's sensor casts the projector's
    /// shadows, and, drawn apart, that its depth is registered to a colour camera
    /// (`ic_data::SensorRanges::set_shadows`: no return beside each nearer edge, on one side
    /// and the other, as structured-light and active-stereo sensors give). Written only when
    /// on.
    #[serde(default, skip_serializing_if = "is_zero_f64")]
    pub shadow_probability: f64,
}

/// The width (network pixels) of [`SegTrainConfig::border_weight`]'s band.
pub const BORDER_SIGMA: f64 = 2.0;

/// The largest weight [`SegTrainConfig::balance_area`] gives a pixel.
pub const BALANCE_CAP: f64 = 4.0;

fn is_zero_f64(v: &f64) -> bool {
    *v == 0.0
}

fn default_core_radius() -> usize {
    2
}

fn default_offset_weight() -> f64 {
    0.5
}

/// Everything a checkpoint records.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SegConfig {
    pub preset: String,
    pub net: UNetConfig,
    pub post: PostConfig,
    pub train: SegTrainConfig,
}

impl SegConfig {
    /// The shipped CPU model: a 4-level U-Net, 8-16-32-128 channels (≈ 0.3 M parameters), on a
    /// 160×120 input; training scenes are rendered at 320×240. Sizes chosen by measurement on
    /// one core (`examples/seg_step_timing.rs`, batch 8): 16-32-64-128 took 7.8 s a step,
    /// 12-24-48-96 5.1 s, 8-16-32-64 3.3 s and 8-16-32-128 3.4 s — the wide coarsest level
    /// (20×15) adds context and parameters for almost no time.
    pub fn cpu() -> Self {
        SegConfig {
            preset: "cpu".into(),
            net: UNetConfig {
                input_width: 160,
                input_height: 120,
                channels: vec![8, 16, 32, 128],
                bn_momentum: 0.1,
                outputs: 1,
                input: SegInput::Depth,
                offset_level: 0,
            },
            post: PostConfig::default(),
            train: SegTrainConfig {
                batch_size: 4,
                learning_rate: 1e-3,
                iterations: 3_000,
                dice_weight: 1.0,
                render_width: 320,
                render_height: 240,
                core_radius: 2,
                offset_weight: default_offset_weight(),
                balance_area: 0.0,
                border_weight: 0.0,
                shadow_probability: 0.0,
            },
        }
    }

    /// Every object of a cluttered scene (`ic_data::clutter`), instance by instance: the `cpu`
    /// network (so its weights can start the training) on 256×192 — 1.6× the `cpu` preset's
    /// width, so a 5 cm object 1.5 m away still spans ≈ 7 input pixels — with the object and
    /// core outputs. Chosen by training cost on one core: a 5-level 8-16-32-64-128 U-Net on
    /// 320×240 took ≈ 4.4 s per batch of 4; this one ≈ half of that (`docs/decisions.md`).
    pub fn clutter() -> Self {
        SegConfig {
            preset: "clutter".into(),
            net: UNetConfig {
                input_width: 256,
                input_height: 192,
                channels: vec![8, 16, 32, 128],
                bn_momentum: 0.1,
                outputs: 2,
                input: SegInput::Depth,
                offset_level: 0,
            },
            post: PostConfig {
                pixel_threshold: 0.5,
                depth_refine_px: 0,
                ..PostConfig::default()
            },
            train: SegTrainConfig {
                batch_size: 4,
                learning_rate: 1e-3,
                iterations: 20_000,
                dice_weight: 1.0,
                render_width: 256,
                render_height: 192,
                core_radius: 2,
                offset_weight: default_offset_weight(),
                balance_area: 0.0,
                border_weight: 0.0,
                shadow_probability: 0.0,
            },
        }
    }

    /// The `clutter` preset with wider channels, 8-24-64-256 (≈ 4× the parameters, ≈ 1.7×
    /// a training step's time on 2 threads), to test whether the `clutter` network lacks
    /// capacity: on clutter scenes of its own training objects it finds the target no more
    /// often than on unseen ones. Measured, not shipped: trained from the `clutter` weights it
    /// found the target no more often (`docs/decisions.md`, "A wider clutter network"). Level 0
    /// (full resolution, most of the arithmetic) keeps 8 channels; the coarser levels, which
    /// see whole objects, get the width. Its training starts from `clutter` weights widened
    /// without changing what they compute (`ic_train::widen`).
    pub fn clutter_wide() -> Self {
        let mut c = Self::clutter();
        c.preset = "clutter-wide".into();
        c.net.channels = vec![8, 24, 64, 256];
        c
    }

    /// The `clutter` preset with the centre-offset outputs (4 outputs): touching objects
    /// whose cores join are cut where the pixels of one core point to two centres. Its
    /// training starts from `clutter` weights, the offset maps at zero
    /// (`Trainer::load_widening`); see `docs/decisions.md`, "Centre offsets".
    pub fn clutter_offsets() -> Self {
        let mut c = Self::clutter();
        c.preset = "clutter-offsets".into();
        c.net.outputs = 4;
        c.post.centres = Some(crate::centres::CentreConfig::default());
        c
    }

    /// The `clutter-offsets` preset with a centre-offset branch on level 2 (32 channels at a
    /// quarter of the input, where a 10 cm object at 1 m is about five pixels wide;
    /// [`UNetConfig::offset_level`]). Its training starts from a `clutter-offsets` (or
    /// `clutter`) checkpoint, the branch's output at zero (`Trainer::load_widening`).
    pub fn clutter_offsets_coarse() -> Self {
        let mut c = Self::clutter_offsets();
        c.preset = "clutter-offsets-coarse".into();
        c.net.offset_level = 2;
        c
    }

    /// The `clutter-offsets` preset with the two finest levels doubled, 16-32-64-128, to
    /// test whether the fine levels (where the band parting two touching objects is drawn)
    /// lack capacity, where `clutter-wide` widened the coarse ones: ≈ 2× a training step's
    /// time on 2 threads, ≈ 1.3× the 640×480 inference. Its training starts from
    /// `clutter-offsets` weights widened without changing what they compute
    /// (`ic_train::widen`); see `docs/decisions.md`, "A network wider where objects part".
    pub fn clutter_offsets_fine() -> Self {
        let mut c = Self::clutter_offsets();
        c.preset = "clutter-offsets-fine".into();
        c.net.channels = vec![16, 32, 64, 128];
        c
    }

    /// A very small network for tests.
    pub fn tiny() -> Self {
        SegConfig {
            preset: "tiny".into(),
            net: UNetConfig {
                input_width: 32,
                input_height: 24,
                channels: vec![4, 8],
                bn_momentum: 0.1,
                outputs: 1,
                input: SegInput::Depth,
                offset_level: 0,
            },
            post: PostConfig {
                min_pixels: 4,
                ..PostConfig::default()
            },
            train: SegTrainConfig {
                batch_size: 2,
                learning_rate: 1e-2,
                iterations: 200,
                dice_weight: 1.0,
                render_width: 64,
                render_height: 48,
                core_radius: 1,
                offset_weight: default_offset_weight(),
                balance_area: 0.0,
                border_weight: 0.0,
                shadow_probability: 0.0,
            },
        }
    }

    pub fn preset(name: &str) -> Result<Self> {
        match name {
            "cpu" => Ok(Self::cpu()),
            "clutter" => Ok(Self::clutter()),
            "clutter-wide" => Ok(Self::clutter_wide()),
            "clutter-offsets" => Ok(Self::clutter_offsets()),
            "clutter-offsets-coarse" => Ok(Self::clutter_offsets_coarse()),
            "clutter-offsets-fine" => Ok(Self::clutter_offsets_fine()),
            "tiny" => Ok(Self::tiny()),
            "tiny-clutter" => {
                let mut c = Self::tiny();
                c.preset = "tiny-clutter".into();
                c.net.outputs = 2;
                Ok(c)
            }
            "tiny-clutter-wide" => {
                let mut c = Self::tiny();
                c.preset = "tiny-clutter-wide".into();
                c.net.outputs = 2;
                c.net.channels = vec![6, 12];
                Ok(c)
            }
            "tiny-clutter-offsets" => {
                let mut c = Self::tiny();
                c.preset = "tiny-clutter-offsets".into();
                c.net.outputs = 4;
                c.post.centres = Some(crate::centres::CentreConfig::default());
                Ok(c)
            }
            "tiny-clutter-offsets-coarse" => {
                let mut c = Self::preset("tiny-clutter-offsets")?;
                c.preset = "tiny-clutter-offsets-coarse".into();
                c.net.offset_level = 1;
                Ok(c)
            }
            other => Err(SegError::Config(format!(
                "unknown preset {other:?} (cpu | clutter | clutter-wide | clutter-offsets | clutter-offsets-coarse | clutter-offsets-fine | tiny | tiny-clutter | tiny-clutter-wide | tiny-clutter-offsets | tiny-clutter-offsets-coarse)"
            ))),
        }
    }

    pub fn validate(&self) -> Result<()> {
        self.net.validate()?;
        let p = &self.post;
        if !(0.0..1.0).contains(&p.pixel_threshold) || !(0.0..1.0).contains(&p.score_threshold) {
            return Err(SegError::Config(
                "pixel_threshold and score_threshold must be in [0, 1)".into(),
            ));
        }
        if !(0.0..1.0).contains(&p.core_threshold) {
            return Err(SegError::Config("core_threshold must be in [0, 1)".into()));
        }
        if !(p.crop_radius > 0.0 && p.crop_radius.is_finite()) {
            return Err(SegError::Config("crop_radius must be positive".into()));
        }
        if let Some(s) = &p.support {
            s.validate()?;
        }
        if let Some(c) = &p.centres {
            c.validate()?;
        }
        if p.extra_inputs.len() > MAX_EXTRA_INPUTS {
            return Err(SegError::Config(format!(
                "{} extra input sizes; at most {MAX_EXTRA_INPUTS}",
                p.extra_inputs.len()
            )));
        }
        for &(w, h) in &p.extra_inputs {
            self.net.check_input("extra input", w, h)?;
        }
        let t = &self.train;
        let weight = |v: f64| v >= 0.0 && v.is_finite();
        if t.batch_size == 0
            || !(t.learning_rate > 0.0)
            || !weight(t.offset_weight)
            || !weight(t.balance_area)
            || !weight(t.border_weight)
            || t.render_width == 0
            || t.render_height == 0
        {
            return Err(SegError::Config(
                "batch_size, learning_rate and the render size must be positive, offset_weight, balance_area and border_weight finite and not negative".into(),
            ));
        }
        if !(0.0..=1.0).contains(&t.shadow_probability) {
            return Err(SegError::Config(format!(
                "shadow_probability must be a probability in [0, 1], got {}",
                t.shadow_probability
            )));
        }
        Ok(())
    }
}
