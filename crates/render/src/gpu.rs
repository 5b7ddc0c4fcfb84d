//! The headless wgpu renderer (no window, no surface).
//!
//! Targets: one `Rg32Uint` colour texture array (x = the f32 bits of the camera-frame z, y =
//! the instance id in the low 16 bits and the quantised incidence cosine in the high 16 bits)
//! and one `Depth32Float` buffer with reversed, infinite-far depth (`z_ndc = near/z`, compare
//! `Greater`, cleared to 0). An integer target works on Vulkan and GL alike (GL cannot render
//! to `R32Float`). Geometry is uploaded once per mesh (`Arc` identity) and kept while the scene
//! uses it; per view only a 256-byte uniform entry per object changes. A batch of views is one
//! submission and one readback (one array layer per view).

use std::sync::{Arc, Weak, mpsc};

use bytemuck::{Pod, Zeroable};
use ic_geometry::Mesh;
use wgpu::util::DeviceExt;

use crate::RenderError;
use crate::renderer::{Camera, Renderer, Rendering, Scene, model_to_camera};

/// Views per submission in [`WgpuRenderer::render_batch`].
const MAX_BATCH: u32 = 16;

/// Options for [`WgpuRenderer::with_options`].
#[derive(Clone, Debug, Default, PartialEq, Eq)]
pub struct WgpuOptions {
    /// A comma-separated backend list as in `WGPU_BACKEND` (`vulkan`, `gl`, …); `None` means
    /// all backends compiled in (Vulkan and GL on Linux).
    pub backends: Option<String>,
    /// Ask for a fallback (software) adapter only.
    pub force_fallback_adapter: bool,
}

impl WgpuOptions {
    /// Options from the environment: `WGPU_BACKEND` when set.
    pub fn from_env() -> Self {
        WgpuOptions {
            backends: std::env::var("WGPU_BACKEND").ok(),
            force_fallback_adapter: false,
        }
    }
}

/// Parses a `WGPU_BACKEND`-style list. Unlike wgpu itself (which ignores unknown names and
/// then finds no adapter), an unknown or empty name is an error.
pub fn parse_backends(value: &str) -> Result<wgpu::Backends, RenderError> {
    let mut out = wgpu::Backends::empty();
    for name in value.split(',') {
        let name = name.trim().to_ascii_lowercase();
        out |= match name.as_str() {
            "vulkan" | "vk" => wgpu::Backends::VULKAN,
            "gl" | "gles" | "opengl" => wgpu::Backends::GL,
            "metal" | "mtl" => wgpu::Backends::METAL,
            "dx12" | "d3d12" => wgpu::Backends::DX12,
            _ => {
                return Err(RenderError::InvalidBackend {
                    value: value.to_string(),
                    name,
                });
            }
        };
    }
    Ok(out)
}

#[repr(C)]
#[derive(Clone, Copy, Pod, Zeroable)]
struct Entry {
    model_view: [f32; 16],
    proj: [f32; 4],
    clip: [f32; 4],
    id: [u32; 4],
}

struct GpuMesh {
    source: Weak<Mesh>,
    vertices: wgpu::Buffer,
    indices: wgpu::Buffer,
    index_count: u32,
}

struct Uniforms {
    buffer: wgpu::Buffer,
    bind_group: wgpu::BindGroup,
    entries: u64,
}

struct Targets {
    width: u32,
    height: u32,
    layers: u32,
    color: wgpu::Texture,
    color_views: Vec<wgpu::TextureView>,
    depth_view: wgpu::TextureView,
    readback: wgpu::Buffer,
    padded_row: u32,
}

/// Headless wgpu renderer: a real GPU when present, else Mesa's lavapipe (software Vulkan).
pub struct WgpuRenderer {
    device: wgpu::Device,
    queue: wgpu::Queue,
    info: wgpu::AdapterInfo,
    pipeline: wgpu::RenderPipeline,
    layout: wgpu::BindGroupLayout,
    stride: u64,
    max_dim: u32,
    meshes: Vec<GpuMesh>,
    uniforms: Option<Uniforms>,
    targets: Option<Targets>,
}

impl std::fmt::Debug for WgpuRenderer {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("WgpuRenderer")
            .field("adapter", &self.info.name)
            .field("backend", &self.info.backend)
            .finish()
    }
}

impl WgpuRenderer {
    /// A renderer on the best adapter, honouring `WGPU_BACKEND` (validated).
    pub fn new() -> Result<Self, RenderError> {
        Self::with_options(&WgpuOptions::from_env())
    }

    /// A renderer with explicit options.
    pub fn with_options(options: &WgpuOptions) -> Result<Self, RenderError> {
        let backends = match &options.backends {
            Some(v) => parse_backends(v)?,
            None => {
                wgpu::Backends::VULKAN
                    | wgpu::Backends::GL
                    | wgpu::Backends::METAL
                    | wgpu::Backends::DX12
            }
        };
        let mut desc = wgpu::InstanceDescriptor::new_without_display_handle();
        desc.backends = backends;
        let instance = wgpu::Instance::new(desc);
        let adapter = pollster::block_on(instance.request_adapter(&wgpu::RequestAdapterOptions {
            power_preference: wgpu::PowerPreference::HighPerformance,
            force_fallback_adapter: options.force_fallback_adapter,
            compatible_surface: None,
            apply_limit_buckets: false,
        }))
        .map_err(|_| RenderError::NoAdapter {
            backends: format!("{backends:?}"),
        })?;
        let info = adapter.get_info();
        let limits = adapter.limits();
        let (device, queue) = pollster::block_on(adapter.request_device(&wgpu::DeviceDescriptor {
            label: Some("ic_render"),
            required_features: wgpu::Features::empty(),
            required_limits: limits.clone(),
            experimental_features: wgpu::ExperimentalFeatures::disabled(),
            memory_hints: wgpu::MemoryHints::Performance,
            trace: wgpu::Trace::Off,
        }))
        .map_err(|e| RenderError::Device {
            adapter: info.name.clone(),
            message: e.to_string(),
        })?;
        tracing::debug!(adapter = %info.name, backend = ?info.backend, "wgpu renderer");

        let entry_size = std::mem::size_of::<Entry>() as u64;
        let align = limits.min_uniform_buffer_offset_alignment.max(1) as u64;
        let stride = entry_size.div_ceil(align) * align;
        let layout = device.create_bind_group_layout(&wgpu::BindGroupLayoutDescriptor {
            label: Some("ic_render entry"),
            entries: &[wgpu::BindGroupLayoutEntry {
                binding: 0,
                visibility: wgpu::ShaderStages::VERTEX | wgpu::ShaderStages::FRAGMENT,
                ty: wgpu::BindingType::Buffer {
                    ty: wgpu::BufferBindingType::Uniform,
                    has_dynamic_offset: true,
                    min_binding_size: wgpu::BufferSize::new(entry_size),
                },
                count: None,
            }],
        });
        let pipeline_layout = device.create_pipeline_layout(&wgpu::PipelineLayoutDescriptor {
            label: Some("ic_render"),
            bind_group_layouts: &[Some(&layout)],
            immediate_size: 0,
        });
        let shader = device.create_shader_module(wgpu::ShaderModuleDescriptor {
            label: Some("ic_render shader"),
            source: wgpu::ShaderSource::Wgsl(include_str!("shader.wgsl").into()),
        });
        let vertex_layout = wgpu::VertexBufferLayout {
            array_stride: 12,
            step_mode: wgpu::VertexStepMode::Vertex,
            attributes: &[wgpu::VertexAttribute {
                format: wgpu::VertexFormat::Float32x3,
                offset: 0,
                shader_location: 0,
            }],
        };
        let pipeline = device.create_render_pipeline(&wgpu::RenderPipelineDescriptor {
            label: Some("ic_render"),
            layout: Some(&pipeline_layout),
            vertex: wgpu::VertexState {
                module: &shader,
                entry_point: Some("vs_main"),
                compilation_options: Default::default(),
                buffers: &[Some(vertex_layout)],
            },
            primitive: wgpu::PrimitiveState {
                topology: wgpu::PrimitiveTopology::TriangleList,
                strip_index_format: None,
                front_face: wgpu::FrontFace::Ccw,
                cull_mode: None,
                unclipped_depth: false,
                polygon_mode: wgpu::PolygonMode::Fill,
                conservative: false,
            },
            depth_stencil: Some(wgpu::DepthStencilState {
                format: wgpu::TextureFormat::Depth32Float,
                depth_write_enabled: Some(true),
                depth_compare: Some(wgpu::CompareFunction::Greater),
                stencil: Default::default(),
                bias: Default::default(),
            }),
            multisample: Default::default(),
            fragment: Some(wgpu::FragmentState {
                module: &shader,
                entry_point: Some("fs_main"),
                compilation_options: Default::default(),
                targets: &[Some(wgpu::ColorTargetState {
                    format: wgpu::TextureFormat::Rg32Uint,
                    blend: None,
                    write_mask: wgpu::ColorWrites::ALL,
                })],
            }),
            multiview_mask: None,
            cache: None,
        });
        Ok(WgpuRenderer {
            device,
            queue,
            info,
            pipeline,
            layout,
            stride,
            max_dim: limits.max_texture_dimension_2d,
            meshes: Vec::new(),
            uniforms: None,
            targets: None,
        })
    }

    /// The adapter in use (name, backend, device type).
    pub fn adapter_info(&self) -> &wgpu::AdapterInfo {
        &self.info
    }

    /// Number of meshes currently uploaded (for tests of the geometry cache).
    pub fn cached_meshes(&self) -> usize {
        self.meshes.len()
    }

    /// Uploads the meshes of `scene` that are not cached yet and drops those no longer used.
    /// Returns, per object, the index of its cached mesh.
    fn sync_meshes(&mut self, scene: &Scene) -> Vec<usize> {
        self.meshes.retain(|m| {
            m.source.strong_count() > 0
                && scene
                    .objects
                    .iter()
                    .any(|o| std::ptr::eq(Arc::as_ptr(&o.mesh), m.source.as_ptr()))
        });
        let mut slots = Vec::with_capacity(scene.objects.len());
        for o in &scene.objects {
            let found = self
                .meshes
                .iter()
                .position(|m| std::ptr::eq(Arc::as_ptr(&o.mesh), m.source.as_ptr()));
            let slot = match found {
                Some(s) => s,
                None => {
                    let flat: Vec<[f32; 3]> =
                        o.mesh.vertices.iter().map(|v| v.to_array()).collect();
                    let vertices =
                        self.device
                            .create_buffer_init(&wgpu::util::BufferInitDescriptor {
                                label: Some("ic_render vertices"),
                                contents: bytemuck::cast_slice(&flat),
                                usage: wgpu::BufferUsages::VERTEX,
                            });
                    let indices =
                        self.device
                            .create_buffer_init(&wgpu::util::BufferInitDescriptor {
                                label: Some("ic_render indices"),
                                contents: bytemuck::cast_slice(&o.mesh.triangles),
                                usage: wgpu::BufferUsages::INDEX,
                            });
                    self.meshes.push(GpuMesh {
                        source: Arc::downgrade(&o.mesh),
                        vertices,
                        indices,
                        index_count: (o.mesh.triangles.len() * 3) as u32,
                    });
                    self.meshes.len() - 1
                }
            };
            slots.push(slot);
        }
        slots
    }

    fn ensure_uniforms(&mut self, entries: u64) {
        if self.uniforms.as_ref().is_some_and(|u| u.entries >= entries) {
            return;
        }
        let entries = entries.next_power_of_two().max(16);
        let buffer = self.device.create_buffer(&wgpu::BufferDescriptor {
            label: Some("ic_render uniforms"),
            size: entries * self.stride,
            usage: wgpu::BufferUsages::UNIFORM | wgpu::BufferUsages::COPY_DST,
            mapped_at_creation: false,
        });
        let bind_group = self.device.create_bind_group(&wgpu::BindGroupDescriptor {
            label: Some("ic_render uniforms"),
            layout: &self.layout,
            entries: &[wgpu::BindGroupEntry {
                binding: 0,
                resource: wgpu::BindingResource::Buffer(wgpu::BufferBinding {
                    buffer: &buffer,
                    offset: 0,
                    size: wgpu::BufferSize::new(std::mem::size_of::<Entry>() as u64),
                }),
            }],
        });
        self.uniforms = Some(Uniforms {
            buffer,
            bind_group,
            entries,
        });
    }

    fn ensure_targets(&mut self, width: u32, height: u32, layers: u32) -> Result<(), RenderError> {
        if width > self.max_dim || height > self.max_dim {
            return Err(RenderError::ImageTooLarge {
                width,
                height,
                max: self.max_dim,
            });
        }
        if self
            .targets
            .as_ref()
            .is_some_and(|t| t.width == width && t.height == height && t.layers >= layers)
        {
            return Ok(());
        }
        let color = self.device.create_texture(&wgpu::TextureDescriptor {
            label: Some("ic_render z+id"),
            size: wgpu::Extent3d {
                width,
                height,
                depth_or_array_layers: layers,
            },
            mip_level_count: 1,
            sample_count: 1,
            dimension: wgpu::TextureDimension::D2,
            format: wgpu::TextureFormat::Rg32Uint,
            usage: wgpu::TextureUsages::RENDER_ATTACHMENT | wgpu::TextureUsages::COPY_SRC,
            view_formats: &[],
        });
        let color_views = (0..layers)
            .map(|layer| {
                color.create_view(&wgpu::TextureViewDescriptor {
                    label: Some("ic_render layer"),
                    dimension: Some(wgpu::TextureViewDimension::D2),
                    base_array_layer: layer,
                    array_layer_count: Some(1),
                    ..Default::default()
                })
            })
            .collect();
        let depth = self.device.create_texture(&wgpu::TextureDescriptor {
            label: Some("ic_render depth"),
            size: wgpu::Extent3d {
                width,
                height,
                depth_or_array_layers: 1,
            },
            mip_level_count: 1,
            sample_count: 1,
            dimension: wgpu::TextureDimension::D2,
            format: wgpu::TextureFormat::Depth32Float,
            usage: wgpu::TextureUsages::RENDER_ATTACHMENT,
            view_formats: &[],
        });
        let depth_view = depth.create_view(&Default::default());
        // Rows of a texture-to-buffer copy are padded to 256 bytes.
        let align = wgpu::COPY_BYTES_PER_ROW_ALIGNMENT;
        let padded_row = (width * 8).div_ceil(align) * align;
        let readback = self.device.create_buffer(&wgpu::BufferDescriptor {
            label: Some("ic_render readback"),
            size: padded_row as u64 * height as u64 * layers as u64,
            usage: wgpu::BufferUsages::MAP_READ | wgpu::BufferUsages::COPY_DST,
            mapped_at_creation: false,
        });
        self.targets = Some(Targets {
            width,
            height,
            layers,
            color,
            color_views,
            depth_view,
            readback,
            padded_row,
        });
        Ok(())
    }

    /// Renders up to `MAX_BATCH` views of the same size in one submission.
    fn render_chunk(
        &mut self,
        scene: &Scene,
        cameras: &[Camera],
    ) -> Result<Vec<Rendering>, RenderError> {
        let (width, height) = (cameras[0].intrinsics.width, cameras[0].intrinsics.height);
        let slots = self.sync_meshes(scene);
        let n_obj = scene.objects.len() as u64;
        let n_views = cameras.len() as u32;
        self.ensure_uniforms((n_obj * n_views as u64).max(1));
        self.ensure_targets(width, height, n_views.max(1))?;

        // Uniforms: one entry per (view, object).
        let mut bytes = vec![0u8; (self.stride * n_obj * n_views as u64) as usize];
        for (vi, cam) in cameras.iter().enumerate() {
            let k = &cam.intrinsics;
            let proj = [
                (2.0 * k.fx / k.width as f64) as f32,
                (2.0 * (k.cx + 0.5) / k.width as f64) as f32,
                (2.0 * k.fy / k.height as f64) as f32,
                (2.0 * (k.cy + 0.5) / k.height as f64) as f32,
            ];
            for (oi, (o, mv)) in scene
                .objects
                .iter()
                .zip(model_to_camera(scene, cam))
                .enumerate()
            {
                let r = mv.rotation;
                let t = mv.translation;
                let model_view = [
                    r.x_axis.x, r.x_axis.y, r.x_axis.z, 0.0, //
                    r.y_axis.x, r.y_axis.y, r.y_axis.z, 0.0, //
                    r.z_axis.x, r.z_axis.y, r.z_axis.z, 0.0, //
                    t.x, t.y, t.z, 1.0,
                ]
                .map(|v| v as f32);
                let e = Entry {
                    model_view,
                    proj,
                    clip: [cam.near as f32, 0.0, 0.0, 0.0],
                    id: [o.id, 0, 0, 0],
                };
                let at = (self.stride * (vi as u64 * n_obj + oi as u64)) as usize;
                bytes[at..at + std::mem::size_of::<Entry>()]
                    .copy_from_slice(bytemuck::bytes_of(&e));
            }
        }
        let uniforms = self.uniforms.as_ref().expect("uniforms allocated");
        let targets = self.targets.as_ref().expect("targets allocated");
        if !bytes.is_empty() {
            self.queue.write_buffer(&uniforms.buffer, 0, &bytes);
        }

        let mut encoder = self
            .device
            .create_command_encoder(&wgpu::CommandEncoderDescriptor {
                label: Some("ic_render"),
            });
        for vi in 0..n_views as usize {
            let mut pass = encoder.begin_render_pass(&wgpu::RenderPassDescriptor {
                label: Some("ic_render view"),
                color_attachments: &[Some(wgpu::RenderPassColorAttachment {
                    view: &targets.color_views[vi],
                    depth_slice: None,
                    resolve_target: None,
                    ops: wgpu::Operations {
                        load: wgpu::LoadOp::Clear(wgpu::Color::TRANSPARENT),
                        store: wgpu::StoreOp::Store,
                    },
                })],
                depth_stencil_attachment: Some(wgpu::RenderPassDepthStencilAttachment {
                    view: &targets.depth_view,
                    depth_ops: Some(wgpu::Operations {
                        load: wgpu::LoadOp::Clear(0.0),
                        store: wgpu::StoreOp::Discard,
                    }),
                    stencil_ops: None,
                }),
                timestamp_writes: None,
                occlusion_query_set: None,
                multiview_mask: None,
            });
            pass.set_pipeline(&self.pipeline);
            for (oi, &slot) in slots.iter().enumerate() {
                let m = &self.meshes[slot];
                let offset = self.stride * (vi as u64 * n_obj + oi as u64);
                pass.set_bind_group(0, &uniforms.bind_group, &[offset as u32]);
                pass.set_vertex_buffer(0, m.vertices.slice(..));
                pass.set_index_buffer(m.indices.slice(..), wgpu::IndexFormat::Uint32);
                pass.draw_indexed(0..m.index_count, 0, 0..1);
            }
        }
        encoder.copy_texture_to_buffer(
            wgpu::TexelCopyTextureInfo {
                texture: &targets.color,
                mip_level: 0,
                origin: wgpu::Origin3d::ZERO,
                aspect: wgpu::TextureAspect::All,
            },
            wgpu::TexelCopyBufferInfo {
                buffer: &targets.readback,
                layout: wgpu::TexelCopyBufferLayout {
                    offset: 0,
                    bytes_per_row: Some(targets.padded_row),
                    rows_per_image: Some(height),
                },
            },
            wgpu::Extent3d {
                width,
                height,
                depth_or_array_layers: n_views,
            },
        );
        self.queue.submit([encoder.finish()]);

        let size = targets.padded_row as u64 * height as u64 * n_views as u64;
        let slice = targets.readback.slice(..size);
        let (tx, rx) = mpsc::channel();
        slice.map_async(wgpu::MapMode::Read, move |r| {
            let _ = tx.send(r);
        });
        self.device
            .poll(wgpu::PollType::wait_indefinitely())
            .map_err(|e| RenderError::Gpu(e.to_string()))?;
        rx.recv()
            .map_err(|_| RenderError::Gpu("readback callback never ran".into()))?
            .map_err(|e| RenderError::Gpu(format!("mapping the readback buffer failed: {e}")))?;
        let mut out = Vec::with_capacity(n_views as usize);
        {
            let data = slice
                .get_mapped_range()
                .map_err(|e| RenderError::Gpu(format!("{e:?}")))?;
            let (w, h) = (width as usize, height as usize);
            let row_bytes = targets.padded_row as usize;
            for vi in 0..n_views as usize {
                let mut r = Rendering::empty(width, height);
                for y in 0..h {
                    let start = (vi * h + y) * row_bytes;
                    let row: &[u32] = bytemuck::cast_slice(&data[start..start + w * 8]);
                    for x in 0..w {
                        let (zbits, packed) = (row[2 * x], row[2 * x + 1]);
                        let id = packed & 0xffff;
                        if id != 0 {
                            let i = y * w + x;
                            r.depth.data[i] = f32::from_bits(zbits);
                            r.instances.data[i] = id;
                            r.incidence.data[i] = (packed >> 16) as f32 / 65535.0;
                        }
                    }
                }
                out.push(r);
            }
        }
        targets.readback.unmap();
        Ok(out)
    }
}

impl Renderer for WgpuRenderer {
    fn render(&mut self, scene: &Scene, camera: &Camera) -> Result<Rendering, RenderError> {
        scene.validate()?;
        camera.validate()?;
        Ok(self
            .render_chunk(scene, std::slice::from_ref(camera))?
            .pop()
            .expect("one view"))
    }

    fn render_batch(
        &mut self,
        scene: &Scene,
        cameras: &[Camera],
    ) -> Result<Vec<Rendering>, RenderError> {
        scene.validate()?;
        for c in cameras {
            c.validate()?;
        }
        let mut out = Vec::with_capacity(cameras.len());
        let mut rest = cameras;
        while !rest.is_empty() {
            // A chunk shares the image size (one texture array).
            let (w, h) = (rest[0].intrinsics.width, rest[0].intrinsics.height);
            let n = rest
                .iter()
                .take(MAX_BATCH as usize)
                .take_while(|c| c.intrinsics.width == w && c.intrinsics.height == h)
                .count();
            out.extend(self.render_chunk(scene, &rest[..n])?);
            rest = &rest[n..];
        }
        Ok(out)
    }

    fn name(&self) -> String {
        format!("wgpu ({}, {:?})", self.info.name, self.info.backend)
    }
}
