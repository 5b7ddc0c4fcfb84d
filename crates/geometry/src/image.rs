//! Dense row-major images: depth maps (metres), instance-id maps and masks.

use crate::GeometryError;

/// A row-major image: pixel (column `u`, row `v`) is `data[v * width + u]`.
#[derive(Clone, Debug, PartialEq)]
pub struct Image<T> {
    pub width: u32,
    pub height: u32,
    pub data: Vec<T>,
}

/// Camera-frame depth z in metres (not the ray length); `0.0` means no return.
pub type DepthImage = Image<f32>;
/// Instance ids; `0` is background.
pub type InstanceImage = Image<u32>;
/// A binary mask; `true` marks the pixels that belong to the object.
pub type Mask = Image<bool>;

impl<T: Clone> Image<T> {
    /// An image filled with `value`.
    pub fn filled(width: u32, height: u32, value: T) -> Self {
        Image {
            width,
            height,
            data: vec![value; width as usize * height as usize],
        }
    }
}

impl Image<bool> {
    /// Binary erosion with a 3×3 square kernel; pixels outside the image count as background
    /// (so the border row and column are always eroded).
    pub fn eroded3x3(&self) -> Mask {
        let (w, h) = (self.width as usize, self.height as usize);
        let mut out = Mask::filled(self.width, self.height, false);
        for y in 1..h.saturating_sub(1) {
            for x in 1..w.saturating_sub(1) {
                out.data[y * w + x] =
                    (y - 1..=y + 1).all(|yy| (x - 1..=x + 1).all(|xx| self.data[yy * w + xx]));
            }
        }
        out
    }

    /// Up to `times` 3×3 erosions ([`Image::eroded3x3`]), stopping before one that would leave
    /// the mask empty: a sliver keeps what there is rather than nothing (the pipeline's
    /// erosion before back-projection, which training samples imitate).
    pub fn eroded3x3_keeping_some(&self, times: usize) -> Mask {
        let mut eroded = self.clone();
        for _ in 0..times {
            let e = eroded.eroded3x3();
            if !e.data.iter().any(|&b| b) {
                break;
            }
            eroded = e;
        }
        eroded
    }
}

impl<T> Image<T> {
    /// Wraps `data`; fails when its length is not `width * height`.
    pub fn from_vec(width: u32, height: u32, data: Vec<T>) -> Result<Self, GeometryError> {
        let expected = width as usize * height as usize;
        if data.len() != expected {
            return Err(GeometryError::LengthMismatch {
                what: "image data vs width*height",
                left: data.len(),
                right: expected,
            });
        }
        Ok(Image {
            width,
            height,
            data,
        })
    }

    /// The pixel at column `u`, row `v`, or `None` outside the image.
    pub fn get(&self, u: u32, v: u32) -> Option<&T> {
        (u < self.width && v < self.height)
            .then(|| &self.data[v as usize * self.width as usize + u as usize])
    }

    /// Fails unless this image is `width`×`height`.
    pub fn check_size(&self, width: u32, height: u32) -> Result<(), GeometryError> {
        if self.width == width && self.height == height {
            Ok(())
        } else {
            Err(GeometryError::ImageSizeMismatch {
                width,
                height,
                got_width: self.width,
                got_height: self.height,
            })
        }
    }
}
