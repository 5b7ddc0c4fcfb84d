//! Depth, mask and instance images on disk.
//!
//! - Depth as a 16-bit grayscale PNG in the BOP convention: `stored value × depth_scale =
//!   millimetres` (0 = no return), or as a 32-bit float OpenEXR with one channel `Z` (reading
//!   also accepts a single `Y` channel), in metres. Reading also takes a one-channel TIFF
//!   (16-bit or 32-bit float samples; BOP's ITODD stores depth so) in the BOP convention.
//! - Masks as 8-bit grayscale PNG (0 / 255; any non-zero value reads as `true`).
//! - Instance ids as 16-bit grayscale PNG.
//!
//! Writes are atomic: the file is written next to its destination under a temporary name and
//! renamed into place, so readers never see a partial file. Every error names the file.

use std::fs::File;
use std::io::{BufReader, BufWriter};
use std::path::Path;

use ic_geometry::{DepthImage, Image, InstanceImage, Mask};

use crate::ImageIoError;

/// The largest image side read or rendered, in pixels (16384: above every depth sensor and
/// 8K frame).
pub const MAX_IMAGE_SIDE: u32 = 16_384;

/// The most pixels of one image read or rendered (2²⁵ ≈ 33.5 M: an 8K UHD frame, 7680×4320,
/// fits). A decoded depth map then stays below ≈ 0.5 GB through the pipeline.
pub const MAX_IMAGE_PIXELS: u64 = 1 << 25;

/// The largest image file read (1 GiB; an uncompressed 16-bit PNG at the largest size is
/// 64 MiB, a float EXR 128 MiB).
pub const MAX_IMAGE_FILE_BYTES: u64 = 1 << 30;

/// Fails with [`ImageIoError::TooLarge`] when `width × height` exceeds [`MAX_IMAGE_SIDE`] or
/// [`MAX_IMAGE_PIXELS`] (checked on headers, before any pixel is decoded, and on cameras
/// before anything is rendered).
pub fn check_image_size(path: &Path, width: u64, height: u64) -> Result<(), ImageIoError> {
    if width > MAX_IMAGE_SIDE as u64
        || height > MAX_IMAGE_SIDE as u64
        || width.saturating_mul(height) > MAX_IMAGE_PIXELS
    {
        return Err(ImageIoError::TooLarge {
            path: path.to_path_buf(),
            width,
            height,
        });
    }
    Ok(())
}

/// Opens an image for reading: a regular file of at most [`MAX_IMAGE_FILE_BYTES`] (device
/// nodes, FIFOs and folders are refused, even behind a symbolic link).
fn open_image(path: &Path) -> Result<BufReader<std::io::Take<File>>, ImageIoError> {
    ic_geometry::io::open_regular(path, MAX_IMAGE_FILE_BYTES)
        .map(BufReader::new)
        .map_err(io_err(path))
}

/// The size of a PNG from its header alone (nothing is decoded); fails when it exceeds the
/// limits of [`check_image_size`].
pub fn png_size(path: impl AsRef<Path>) -> Result<(u32, u32), ImageIoError> {
    let path = path.as_ref();
    let reader = png::Decoder::new(open_image(path)?)
        .read_info()
        .map_err(|e| codec(path, e))?;
    let info = reader.info();
    check_image_size(path, info.width as u64, info.height as u64)?;
    Ok((info.width, info.height))
}

/// The size of an OpenEXR image's first valid layer from its header alone; fails when it
/// exceeds the limits of [`check_image_size`].
pub fn exr_size(path: impl AsRef<Path>) -> Result<(u32, u32), ImageIoError> {
    let path = path.as_ref();
    let meta = exr::meta::MetaData::read_from_buffered(open_image(path)?, false)
        .map_err(|e| codec(path, e))?;
    let first = meta
        .headers
        .first()
        .ok_or_else(|| codec(path, "the file has no image layer"))?;
    // Every layer is bounded, not only the first: the reader looks at all of them.
    for header in &meta.headers {
        let size = header.layer_size;
        check_image_size(path, size.width() as u64, size.height() as u64)?;
    }
    let size = first.layer_size;
    Ok((size.width() as u32, size.height() as u32))
}

fn io_err(path: &Path) -> impl Fn(std::io::Error) -> ImageIoError + '_ {
    move |source| ImageIoError::Io {
        path: path.to_path_buf(),
        source,
    }
}

fn codec(path: &Path, e: impl std::fmt::Display) -> ImageIoError {
    ImageIoError::Codec {
        path: path.to_path_buf(),
        message: e.to_string(),
    }
}

/// Writes `path` atomically: `write` fills a temporary file in the same directory, which is
/// then renamed over `path`. The temporary file is removed on failure.
pub fn write_atomic(
    path: &Path,
    write: impl FnOnce(&mut BufWriter<File>) -> Result<(), ImageIoError>,
) -> Result<(), ImageIoError> {
    ic_geometry::io::write_atomic_with(path, write, io_err(path))
}

fn write_png_gray(
    path: &Path,
    width: u32,
    height: u32,
    depth: png::BitDepth,
    data: &[u8],
) -> Result<(), ImageIoError> {
    write_atomic(path, |w| {
        let mut enc = png::Encoder::new(w, width, height);
        enc.set_color(png::ColorType::Grayscale);
        enc.set_depth(depth);
        let mut writer = enc.write_header().map_err(|e| codec(path, e))?;
        writer.write_image_data(data).map_err(|e| codec(path, e))?;
        writer.finish().map_err(|e| codec(path, e))
    })
}

/// Reads a single-channel PNG of the given bit depth; returns (width, height, raw bytes).
fn read_png_gray(
    path: &Path,
    bits: png::BitDepth,
    expected: Option<(u32, u32)>,
) -> Result<(u32, u32, Vec<u8>), ImageIoError> {
    let mut dec = png::Decoder::new(open_image(path)?);
    dec.set_transformations(png::Transformations::IDENTITY);
    let mut reader = dec.read_info().map_err(|e| codec(path, e))?;
    let (width, height, color, depth) = {
        let info = reader.info();
        (info.width, info.height, info.color_type, info.bit_depth)
    };
    if color != png::ColorType::Grayscale || depth != bits {
        return Err(ImageIoError::Format {
            path: path.to_path_buf(),
            expected: format!("a single-channel (grayscale) {}-bit PNG", bits as u8),
            found: format!(
                "{color:?} ({} channel(s)), {}-bit",
                color.samples(),
                depth as u8
            ),
        });
    }
    check_size(path, width, height, expected)?;
    check_image_size(path, width as u64, height as u64)?;
    let size = reader
        .output_buffer_size()
        .ok_or_else(|| codec(path, "image too large"))?;
    let mut buf = vec![0u8; size];
    let info = reader.next_frame(&mut buf).map_err(|e| codec(path, e))?;
    buf.truncate(info.buffer_size());
    Ok((width, height, buf))
}

fn check_size(
    path: &Path,
    got_width: u32,
    got_height: u32,
    expected: Option<(u32, u32)>,
) -> Result<(), ImageIoError> {
    match expected {
        Some((width, height)) if (width, height) != (got_width, got_height) => {
            Err(ImageIoError::SizeMismatch {
                path: path.to_path_buf(),
                width,
                height,
                got_width,
                got_height,
            })
        }
        _ => Ok(()),
    }
}

fn check_scale(path: &Path, depth_scale: f64) -> Result<(), ImageIoError> {
    if depth_scale.is_finite() && depth_scale > 0.0 {
        Ok(())
    } else {
        Err(ImageIoError::InvalidParameter {
            path: path.to_path_buf(),
            message: format!("depth scale must be positive and finite, got {depth_scale}"),
        })
    }
}

/// Writes depth (metres, 0 = no return) as a 16-bit PNG with `stored × depth_scale = mm`
/// (BOP; `depth_scale = 1.0` stores whole millimetres, 0.1 tenths of a millimetre). Fails on a
/// negative or non-finite depth or one that does not fit 16 bits.
pub fn write_depth_png(
    path: impl AsRef<Path>,
    depth: &DepthImage,
    depth_scale: f64,
) -> Result<(), ImageIoError> {
    let path = path.as_ref();
    check_scale(path, depth_scale)?;
    let w = depth.width as usize;
    let mut bytes = Vec::with_capacity(depth.data.len() * 2);
    for (i, &z) in depth.data.iter().enumerate() {
        let stored = z as f64 * 1000.0 / depth_scale;
        let (u, v) = ((i % w) as u32, (i / w) as u32);
        if !(z.is_finite() && z >= 0.0) || stored.round() > u16::MAX as f64 {
            return Err(ImageIoError::ValueOutOfRange {
                path: path.to_path_buf(),
                u,
                v,
                message: format!(
                    "depth {z} m cannot be stored as a 16-bit value at depth scale {depth_scale} (largest {:.3} m)",
                    u16::MAX as f64 * depth_scale / 1000.0
                ),
            });
        }
        bytes.extend_from_slice(&(stored.round() as u16).to_be_bytes());
    }
    write_png_gray(
        path,
        depth.width,
        depth.height,
        png::BitDepth::Sixteen,
        &bytes,
    )
}

/// A stored depth sample in the BOP convention (`stored × depth_scale = mm`), in metres.
fn stored_to_metres(stored: f64, depth_scale: f64) -> f32 {
    (stored * depth_scale / 1000.0) as f32
}

/// Reads a 16-bit depth PNG written with `depth_scale` back to metres. `expected` checks the
/// size.
pub fn read_depth_png(
    path: impl AsRef<Path>,
    depth_scale: f64,
    expected: Option<(u32, u32)>,
) -> Result<DepthImage, ImageIoError> {
    let path = path.as_ref();
    check_scale(path, depth_scale)?;
    let (w, h, bytes) = read_png_gray(path, png::BitDepth::Sixteen, expected)?;
    let data = bytes
        .chunks_exact(2)
        .map(|c| stored_to_metres(u16::from_be_bytes([c[0], c[1]]) as f64, depth_scale))
        .collect();
    Ok(Image {
        width: w,
        height: h,
        data,
    })
}

/// The size of a TIFF's first image from its header alone; fails when it exceeds the limits of
/// [`check_image_size`].
pub fn tiff_size(path: impl AsRef<Path>) -> Result<(u32, u32), ImageIoError> {
    open_tiff(path.as_ref()).map(|(_, size)| size)
}

/// A TIFF decoder at its first image, and that image's size (checked against
/// [`check_image_size`] before any pixel is decoded).
type TiffDecoder = tiff::decoder::Decoder<BufReader<std::io::Take<File>>>;
fn open_tiff(path: &Path) -> Result<(TiffDecoder, (u32, u32)), ImageIoError> {
    let mut decoder = tiff::decoder::Decoder::new(open_image(path)?).map_err(|e| codec(path, e))?;
    let (w, h) = decoder.dimensions().map_err(|e| codec(path, e))?;
    check_image_size(path, w as u64, h as u64)?;
    Ok((decoder, (w, h)))
}

/// Reads the first image of a one-channel TIFF depth map in the BOP convention (`stored ×
/// depth_scale = mm`, 0 = no return) back to metres: 16-bit unsigned or 32-bit float samples
/// (a float map is scaled the same way; its non-finite and negative samples read as 0).
/// `expected` checks the size, before any pixel is decoded.
pub fn read_depth_tiff(
    path: impl AsRef<Path>,
    depth_scale: f64,
    expected: Option<(u32, u32)>,
) -> Result<DepthImage, ImageIoError> {
    use tiff::ColorType;
    use tiff::decoder::DecodingResult;
    let path = path.as_ref();
    check_scale(path, depth_scale)?;
    let (mut decoder, (w, h)) = open_tiff(path)?;
    check_size(path, w, h, expected)?;
    let format = |found: String| ImageIoError::Format {
        path: path.to_path_buf(),
        expected: "one channel of 16-bit unsigned or 32-bit float samples".into(),
        found,
    };
    match decoder.colortype().map_err(|e| codec(path, e))? {
        ColorType::Gray(16 | 32) => {}
        other => return Err(format(format!("{other:?}"))),
    }
    let data: Vec<f32> = match decoder.read_image().map_err(|e| codec(path, e))? {
        DecodingResult::U16(v) => v
            .into_iter()
            .map(|x| stored_to_metres(x as f64, depth_scale))
            .collect(),
        // A float map's non-finite and negative samples are missing returns.
        DecodingResult::F32(v) => v
            .into_iter()
            .map(|x| {
                if x.is_finite() && x > 0.0 {
                    stored_to_metres(x as f64, depth_scale)
                } else {
                    0.0
                }
            })
            .collect(),
        other => {
            let kind = match other {
                DecodingResult::U32(_) => "32-bit unsigned",
                DecodingResult::I16(_) => "16-bit signed",
                DecodingResult::I32(_) => "32-bit signed",
                _ => "other",
            };
            return Err(format(format!("{kind} samples")));
        }
    };
    ic_geometry::Image::from_vec(w, h, data).map_err(|e| codec(path, e))
}

/// Writes a mask as an 8-bit PNG (255 = true, 0 = false).
pub fn write_mask_png(path: impl AsRef<Path>, mask: &Mask) -> Result<(), ImageIoError> {
    let bytes: Vec<u8> = mask.data.iter().map(|&m| if m { 255 } else { 0 }).collect();
    write_png_gray(
        path.as_ref(),
        mask.width,
        mask.height,
        png::BitDepth::Eight,
        &bytes,
    )
}

/// Reads an 8-bit mask PNG (non-zero = true).
pub fn read_mask_png(
    path: impl AsRef<Path>,
    expected: Option<(u32, u32)>,
) -> Result<Mask, ImageIoError> {
    let (w, h, bytes) = read_png_gray(path.as_ref(), png::BitDepth::Eight, expected)?;
    Ok(Image {
        width: w,
        height: h,
        data: bytes.into_iter().map(|b| b != 0).collect(),
    })
}

/// Writes instance ids as a 16-bit PNG; fails on an id above 65535.
pub fn write_instances_png(
    path: impl AsRef<Path>,
    ids: &InstanceImage,
) -> Result<(), ImageIoError> {
    let path = path.as_ref();
    let w = ids.width as usize;
    let mut bytes = Vec::with_capacity(ids.data.len() * 2);
    for (i, &id) in ids.data.iter().enumerate() {
        let v = u16::try_from(id).map_err(|_| ImageIoError::ValueOutOfRange {
            path: path.to_path_buf(),
            u: (i % w) as u32,
            v: (i / w) as u32,
            message: format!("instance id {id} does not fit 16 bits"),
        })?;
        bytes.extend_from_slice(&v.to_be_bytes());
    }
    write_png_gray(path, ids.width, ids.height, png::BitDepth::Sixteen, &bytes)
}

/// Reads a 16-bit instance-id PNG.
pub fn read_instances_png(
    path: impl AsRef<Path>,
    expected: Option<(u32, u32)>,
) -> Result<InstanceImage, ImageIoError> {
    let (w, h, bytes) = read_png_gray(path.as_ref(), png::BitDepth::Sixteen, expected)?;
    Ok(Image {
        width: w,
        height: h,
        data: bytes
            .chunks_exact(2)
            .map(|c| u16::from_be_bytes([c[0], c[1]]) as u32)
            .collect(),
    })
}

/// Writes depth in metres as a single-channel (`Z`) 32-bit float OpenEXR (lossless ZIP).
pub fn write_depth_exr(path: impl AsRef<Path>, depth: &DepthImage) -> Result<(), ImageIoError> {
    use exr::prelude::*;
    let path = path.as_ref();
    let (w, h) = (depth.width as usize, depth.height as usize);
    if w == 0 || h == 0 {
        return Err(ImageIoError::InvalidParameter {
            path: path.to_path_buf(),
            message: "the image is empty".into(),
        });
    }
    let channel = AnyChannel::new("Z", FlatSamples::F32(depth.data.clone()));
    let layer = Layer::new(
        (w, h),
        LayerAttributes::default(),
        Encoding::SMALL_LOSSLESS,
        AnyChannels::sort(SmallVec::from_vec(vec![channel])),
    );
    let image = exr::image::Image::from_layer(layer);
    write_atomic(path, |out| {
        image.write().to_buffered(out).map_err(|e| codec(path, e))
    })
}

/// Reads a single-channel (`Z` or `Y`) OpenEXR depth map (f32 or f16 samples) in metres.
pub fn read_depth_exr(
    path: impl AsRef<Path>,
    expected: Option<(u32, u32)>,
) -> Result<DepthImage, ImageIoError> {
    use exr::prelude::*;
    let path = path.as_ref();
    // The header first: its size is checked before the decoder allocates any pixel.
    let (w, h) = exr_size(path)?;
    check_size(path, w, h, expected)?;
    let image = read()
        .no_deep_data()
        .largest_resolution_level()
        .all_channels()
        .first_valid_layer()
        .all_attributes()
        .from_buffered(open_image(path)?)
        .map_err(|e| codec(path, e))?;
    let layer = &image.layer_data;
    let names: Vec<String> = layer
        .channel_data
        .list
        .iter()
        .map(|c| c.name.to_string())
        .collect();
    if names.len() != 1 || !(names[0] == "Z" || names[0] == "Y") {
        return Err(ImageIoError::Format {
            path: path.to_path_buf(),
            expected: "one channel named Z or Y".into(),
            found: format!("{} channel(s) {names:?}", names.len()),
        });
    }
    let (w, h) = (layer.size.width() as u32, layer.size.height() as u32);
    check_size(path, w, h, expected)?;
    let data: Vec<f32> = match &layer.channel_data.list[0].sample_data {
        FlatSamples::F32(v) => v.clone(),
        FlatSamples::F16(v) => v.iter().map(|x| x.to_f32()).collect(),
        FlatSamples::U32(_) => {
            return Err(ImageIoError::Format {
                path: path.to_path_buf(),
                expected: "float samples (f32 or f16)".into(),
                found: "u32 samples".into(),
            });
        }
    };
    ic_geometry::Image::from_vec(w, h, data).map_err(|e| codec(path, e))
}
