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
