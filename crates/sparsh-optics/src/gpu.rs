//! The image-formation models as wgpu compute shaders (`shaders/*.wgsl` at the repository root):
//! the same maths as the CPU path in f32, one invocation per pixel, so the image of a surface is
//! the same on every run. Buffers and the pipeline are made once per renderer and reused for
//! every frame; only the surface (with shadows, and its tile bounds for the shortcuts of
//! [`crate::shadow::light_visibility`]) is uploaded and the image read back before rounding,
//! which the CPU does as on its own path.

use std::sync::{Arc, Mutex, OnceLock};

use image::RgbImage;
use wgpu::util::DeviceExt;

use sparsh_scene::Light;

use crate::photometric::camera_mm;
use crate::shadow::{HeightField, MIN_TILE_SHIFT, ShadowSettings};
use crate::{CalibratedRenderer, PhotometricRenderer, Renderer, Surface};

const COMMON_WGSL: &str = include_str!("../../../shaders/common.wgsl");
const PHOTOMETRIC_WGSL: &str = include_str!("../../../shaders/photometric.wgsl");
const CALIBRATED_WGSL: &str = include_str!("../../../shaders/calibrated.wgsl");
/// Workgroup edge of the shaders (`@workgroup_size(8, 8)`).
const WORKGROUP: u32 = 8;

/// GPU failures.
#[derive(Debug, Clone, thiserror::Error)]
pub enum GpuError {
    /// wgpu found no adapter (no GPU and no software driver such as Mesa's lavapipe).
    #[error("no GPU adapter found ({0}); install a Vulkan driver (e.g. apt mesa-vulkan-drivers)")]
    NoAdapter(String),
    /// The adapter refused a device, a shader or a buffer.
    #[error("GPU: {0}")]
    Device(String),
}

/// A wgpu device and queue, shared by every GPU renderer of the process.
#[derive(Debug, Clone)]
pub struct GpuContext {
    device: wgpu::Device,
    queue: wgpu::Queue,
    adapter: String,
}

impl GpuContext {
    /// The process's GPU context, made on first use (the adapter wgpu prefers; `WGPU_BACKEND`
    /// and `WGPU_ADAPTER_NAME` choose another).
    pub fn shared() -> Result<GpuContext, GpuError> {
        static SHARED: OnceLock<Result<GpuContext, GpuError>> = OnceLock::new();
        SHARED.get_or_init(GpuContext::new).clone()
    }

    fn new() -> Result<GpuContext, GpuError> {
        let instance =
            wgpu::Instance::new(wgpu::InstanceDescriptor::new_without_display_handle_from_env());
        let adapter = pollster::block_on(instance.request_adapter(&wgpu::RequestAdapterOptions {
            power_preference: wgpu::PowerPreference::HighPerformance,
            ..Default::default()
        }))
        .map_err(|e| GpuError::NoAdapter(e.to_string()))?;
        let info = adapter.get_info();
        let (device, queue) = pollster::block_on(adapter.request_device(&wgpu::DeviceDescriptor {
            label: Some("sparsh-optics"),
            required_limits: wgpu::Limits::downlevel_defaults(),
            ..Default::default()
        }))
        .map_err(|e| GpuError::Device(format!("{}: {e}", info.name)))?;
        let kind = match info.device_type {
            wgpu::DeviceType::DiscreteGpu => "a discrete GPU",
            wgpu::DeviceType::IntegratedGpu => "an integrated GPU",
            wgpu::DeviceType::VirtualGpu => "a virtual GPU",
            wgpu::DeviceType::Cpu => "a software rasteriser on the CPU",
            wgpu::DeviceType::Other => "a device of unknown type",
        };
        Ok(GpuContext {
            device,
            queue,
            adapter: format!("{} ({:?}, {kind})", info.name, info.backend),
        })
    }

    /// The adapter's name, backend and kind, e.g. `llvmpipe (LLVM 15.0.6, 256 bits) (Vulkan, a
    /// software rasteriser on the CPU)`.
    pub fn adapter(&self) -> &str {
        &self.adapter
    }
}

/// The uniform block of `shaders/common.wgsl`.
#[repr(C)]
#[derive(Debug, Clone, Copy, Default, bytemuck::Pod, bytemuck::Zeroable)]
struct Params {
    width: u32,
    height: u32,
    lights: u32,
    nodes: u32,
    shadow_steps: u32,
    perspective: u32,
    tile_shift: u32,
    tile_offset: u32,
    cell_mm: f32,
    gain: f32,
    specular: f32,
    shininess: f32,
    camera_z_mm: f32,
    max_march_mm: f32,
    led_radius_mm: f32,
    max_height_mm: f32,
    height_tol_mm: f32,
    unused: [f32; 3],
}

impl Params {
    fn shadows(self, settings: Option<ShadowSettings>) -> Params {
        match settings {
            Some(s) => Params {
                shadow_steps: s.steps,
                max_march_mm: s.max_march_mm as f32,
                led_radius_mm: s.led_radius_mm as f32,
                ..self
            },
            None => self,
        }
    }
}

/// One of the models on the GPU, with its buffers and pipeline made once.
#[derive(Debug, Clone)]
pub struct GpuRenderer {
    /// The CPU model (for its background image).
    cpu: Box<Renderer>,
    context: GpuContext,
    /// The model's uniforms but for the frame's cell size and highest point.
    uniforms: Params,
    pipeline: wgpu::ComputePipeline,
    bind_group: wgpu::BindGroup,
    params: wgpu::Buffer,
    surface: wgpu::Buffer,
    output: wgpu::Buffer,
    readback: wgpu::Buffer,
    /// Surface fields uploaded per frame: u_z, or u_z, u_x, u_y.
    fields: usize,
    width_px: usize,
    height_px: usize,
    /// Frames share the buffers: one at a time.
    busy: Arc<Mutex<()>>,
}

impl GpuRenderer {
    /// Puts a CPU model on the GPU.
    pub fn new(model: &Renderer, context: &GpuContext) -> Result<GpuRenderer, GpuError> {
        match model {
            Renderer::Photometric(r) => photometric(r, context),
            Renderer::Calibrated(r) => calibrated(r, context),
            Renderer::Gpu(r) => Ok(r.clone()),
        }
    }

    /// The no-contact image.
    pub fn background(&self) -> RgbImage {
        self.cpu.background()
    }

    /// The image of a deformed surface (its grid must match the image size).
    pub fn render(&self, surface: &Surface) -> Result<RgbImage, GpuError> {
        let pixels = self.render_linear(surface)?;
        Ok(crate::to_image(self.width_px, self.height_px, &pixels))
    }

    /// The image of a deformed surface before rounding (RGB, 0–255 scale).
    pub fn render_linear(&self, surface: &Surface) -> Result<Vec<[f32; 3]>, GpuError> {
        self.render_frame(surface, true)
    }

    /// [`GpuRenderer::render_linear`] with or without the shadows' tile shortcuts (the same
    /// image).
    fn render_frame(&self, surface: &Surface, shortcuts: bool) -> Result<Vec<[f32; 3]>, GpuError> {
        assert_eq!(
            (surface.grid.nx, surface.grid.ny),
            (self.width_px, self.height_px),
            "surface grid and image differ in size"
        );
        let fields = [surface.uz_mm, surface.ux_mm, surface.uy_mm];
        let mut data: Vec<f32> = fields[..self.fields]
            .iter()
            .flat_map(|f| f.iter().map(|&v| v as f32))
            .collect();
        let mut params = Params {
            cell_mm: surface.grid.cell_mm as f32,
            ..self.uniforms
        };
        if params.shadow_steps > 0 {
            let field = HeightField::from_uz(surface.uz_mm, surface.grid);
            params.max_height_mm = field.max_mm as f32;
            if shortcuts {
                push_tile_bounds(&field, &mut params, &mut data);
            }
        }
        let _busy = self.busy.lock().unwrap_or_else(|e| e.into_inner());
        let ctx = &self.context;
        ctx.queue
            .write_buffer(&self.params, 0, bytemuck::bytes_of(&params));
        ctx.queue
            .write_buffer(&self.surface, 0, bytemuck::cast_slice(&data));
        let mut encoder = ctx
            .device
            .create_command_encoder(&wgpu::CommandEncoderDescriptor::default());
        {
            let mut pass = encoder.begin_compute_pass(&wgpu::ComputePassDescriptor::default());
            pass.set_pipeline(&self.pipeline);
            pass.set_bind_group(0, &self.bind_group, &[]);
            pass.dispatch_workgroups(
                (self.width_px as u32).div_ceil(WORKGROUP),
                (self.height_px as u32).div_ceil(WORKGROUP),
                1,
            );
        }
        encoder.copy_buffer_to_buffer(&self.output, 0, &self.readback, 0, self.output.size());
        ctx.queue.submit([encoder.finish()]);
        let (tx, rx) = std::sync::mpsc::channel();
        self.readback
            .map_async(wgpu::MapMode::Read, .., move |r| drop(tx.send(r)));
        let device_error = |e: &dyn std::fmt::Display| GpuError::Device(e.to_string());
        ctx.device
            .poll(wgpu::PollType::wait_indefinitely())
            .map_err(|e| device_error(&e))?;
        rx.recv()
            .map_err(|e| device_error(&e))?
            .map_err(|e| device_error(&e))?;
        let pixels = {
            let view = self
                .readback
                .get_mapped_range(..)
                .map_err(|e| device_error(&e))?;
            bytemuck::cast_slice::<u8, [f32; 4]>(&view)
                .iter()
                .map(|p| [p[0], p[1], p[2]])
                .collect()
        };
        self.readback.unmap();
        Ok(pixels)
    }
}

/// Appends the shadow shortcuts' tile bounds of `field` to the surface data (per tile: the
/// block's highest point and steepest slopes along x and y, as [`light_visibility`] uses them)
/// and sets their uniforms.
///
/// [`light_visibility`]: crate::shadow::light_visibility
fn push_tile_bounds(field: &HeightField, params: &mut Params, data: &mut Vec<f32>) {
    let g = field.grid;
    // Conservative: a height the shader samples may exceed the f64 field's bounds by a few f32
    // roundings of heights up to H = max |h| and of positions up to N cells (moved along slopes
    // up to S); 2^-18 covers 32 ulps of each.
    let h = field.height_mm.iter().fold(0.0f64, |m, h| m.max(h.abs()));
    let s = field
        .block_slope
        .iter()
        .fold(0.0f64, |m, s| m.max(s[0] + s[1]));
    let extent_mm = g.nx.max(g.ny) as f64 * g.cell_mm;
    params.height_tol_mm = ((h + extent_mm * s) / f64::from(1 << 18)) as f32;
    params.tile_shift = field.tile_shift;
    params.tile_offset = data.len() as u32;
    for (m, s) in field.block_max_mm.iter().zip(&field.block_slope) {
        data.extend([*m as f32, s[0] as f32, s[1] as f32]);
    }
}

fn rgb(v: [f32; 3]) -> [f32; 4] {
    [v[0], v[1], v[2], 0.0]
}

/// Each light as (position, intensity), (colour, 0).
fn push_lights(model: &mut Vec<[f32; 4]>, lights: &[Light]) {
    for light in lights {
        let [x, y, z] = light.position_mm.map(|v| v as f32);
        model.push([x, y, z, light.intensity as f32]);
        model.push(rgb(light.color.map(|v| v as f32)));
    }
}

fn photometric(r: &PhotometricRenderer, context: &GpuContext) -> Result<GpuRenderer, GpuError> {
    let sensor = &r.sensor;
    let mut model: Vec<[f32; 4]> = r.background.iter().copied().map(rgb).collect();
    model.extend(
        r.flat
            .iter()
            .zip(&r.vignette)
            .map(|(f, v)| [f[0], f[1], f[2], *v]),
    );
    push_lights(&mut model, &sensor.lights);
    let camera = camera_mm(sensor);
    let uniforms = Params {
        width: sensor.width_px as u32,
        height: sensor.height_px as u32,
        lights: sensor.lights.len() as u32,
        perspective: u32::from(camera.is_some()),
        gain: r.gain,
        specular: sensor.specular as f32,
        shininess: sensor.shininess as f32,
        camera_z_mm: camera.map_or(0.0, |c| c[2] as f32),
        ..Params::default()
    }
    .shadows(r.shadows);
    build(
        Renderer::Photometric(r.clone()),
        context,
        PHOTOMETRIC_WGSL,
        &model,
        uniforms,
        3,
    )
}

fn calibrated(r: &CalibratedRenderer, context: &GpuContext) -> Result<GpuRenderer, GpuError> {
    let mut model: Vec<[f32; 4]> = r
        .background
        .iter()
        .chain(&r.map.coef)
        .copied()
        .map(rgb)
        .collect();
    let mut uniforms = Params {
        width: r.width_px as u32,
        height: r.height_px as u32,
        nodes: r.map.nodes as u32,
        ..Params::default()
    };
    if let Some(sh) = &r.shadows {
        model.extend(sh.shares.iter().copied().map(rgb));
        push_lights(&mut model, &sh.lights);
        uniforms.lights = sh.lights.len() as u32;
        uniforms = uniforms.shadows(Some(sh.settings));
    }
    build(
        Renderer::Calibrated(r.clone()),
        context,
        CALIBRATED_WGSL,
        &model,
        uniforms,
        1,
    )
}

/// Compiles the model's shader and makes its buffers.
fn build(
    cpu: Renderer,
    context: &GpuContext,
    shader: &str,
    model: &[[f32; 4]],
    uniforms: Params,
    fields: usize,
) -> Result<GpuRenderer, GpuError> {
    let (width_px, height_px) = (uniforms.width as usize, uniforms.height as usize);
    let device = &context.device;
    let scope = device.push_error_scope(wgpu::ErrorFilter::Validation);
    let pixels = (width_px * height_px) as u64;
    // with shadows, room for the bounds of the smallest tiles
    let tile = 1 << MIN_TILE_SHIFT;
    let tile_values = match uniforms.shadow_steps {
        0 => 0,
        _ => 3 * width_px.div_ceil(tile) * height_px.div_ceil(tile),
    };
    let module = device.create_shader_module(wgpu::ShaderModuleDescriptor {
        label: Some("sparsh-optics"),
        source: wgpu::ShaderSource::Wgsl([COMMON_WGSL, shader].concat().into()),
    });
    let pipeline = device.create_compute_pipeline(&wgpu::ComputePipelineDescriptor {
        label: Some("sparsh-optics"),
        layout: None,
        module: &module,
        entry_point: Some("main"),
        compilation_options: Default::default(),
        cache: None,
    });
    let params = device.create_buffer(&wgpu::BufferDescriptor {
        label: Some("params"),
        size: size_of::<Params>() as u64,
        usage: wgpu::BufferUsages::UNIFORM | wgpu::BufferUsages::COPY_DST,
        mapped_at_creation: false,
    });
    let surface = device.create_buffer(&wgpu::BufferDescriptor {
        label: Some("surface"),
        size: (pixels * fields as u64 + tile_values as u64) * 4,
        usage: wgpu::BufferUsages::STORAGE | wgpu::BufferUsages::COPY_DST,
        mapped_at_creation: false,
    });
    let model = device.create_buffer_init(&wgpu::util::BufferInitDescriptor {
        label: Some("model"),
        contents: bytemuck::cast_slice(model),
        usage: wgpu::BufferUsages::STORAGE,
    });
    let output = device.create_buffer(&wgpu::BufferDescriptor {
        label: Some("image"),
        size: pixels * 16,
        usage: wgpu::BufferUsages::STORAGE | wgpu::BufferUsages::COPY_SRC,
        mapped_at_creation: false,
    });
    let readback = device.create_buffer(&wgpu::BufferDescriptor {
        label: Some("readback"),
        size: pixels * 16,
        usage: wgpu::BufferUsages::MAP_READ | wgpu::BufferUsages::COPY_DST,
        mapped_at_creation: false,
    });
    let entries = [&params, &surface, &model, &output]
        .iter()
        .enumerate()
        .map(|(binding, buffer)| wgpu::BindGroupEntry {
            binding: binding as u32,
            resource: buffer.as_entire_binding(),
        })
        .collect::<Vec<_>>();
    let bind_group = device.create_bind_group(&wgpu::BindGroupDescriptor {
        label: Some("sparsh-optics"),
        layout: &pipeline.get_bind_group_layout(0),
        entries: &entries,
    });
    if let Some(e) = pollster::block_on(scope.pop()) {
        return Err(GpuError::Device(e.to_string()));
    }
    Ok(GpuRenderer {
        cpu: Box::new(cpu),
        context: context.clone(),
        uniforms,
        pipeline,
        bind_group,
        params,
        surface,
        output,
        readback,
        fields,
        width_px,
        height_px,
        busy: Arc::new(Mutex::new(())),
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::photometric::shadow_settings;
    use sparsh_scene::SensorConfig;

    /// The tile shortcuts change nothing on the GPU either: every pixel of ball presses under
    /// two presets' LEDs equals the full march's, bit for bit.
    #[test]
    fn the_tile_shortcuts_are_exact_on_the_gpu() {
        let context = match GpuContext::shared() {
            Ok(context) => context,
            Err(e) if std::env::var("SPARSH_REQUIRE_GPU").as_deref() == Ok("1") => {
                panic!("SPARSH_REQUIRE_GPU=1 but {e}")
            }
            Err(e) => return eprintln!("skipped: {e}"),
        };
        for (preset, w, h) in [("gelsight2017", 320, 240), ("digit", 640, 480)] {
            let mut sensor = SensorConfig::preset(preset).unwrap();
            sensor.mm_per_px *= sensor.width_px as f64 / w as f64;
            (sensor.width_px, sensor.height_px) = (w, h);
            let grid = sensor.grid();
            let cpu =
                PhotometricRenderer::new(&sensor, Some(shadow_settings(&sensor, 32))).unwrap();
            let gpu = GpuRenderer::new(&Renderer::Photometric(cpu), &context).unwrap();
            for (centre, radius) in [([1.0, -0.5], 1.2), ([-2.0, 1.5], 1.8)] {
                let uz = crate::ball::ball_press_uz_mm(grid, centre, radius, 2.0).unwrap();
                let zeros = vec![0.0; grid.len()];
                let surface = Surface {
                    grid,
                    ux_mm: &zeros,
                    uy_mm: &zeros,
                    uz_mm: &uz,
                };
                let fast = gpu.render_frame(&surface, true).unwrap();
                let full = gpu.render_frame(&surface, false).unwrap();
                let differ = fast.iter().zip(&full).filter(|(a, b)| a != b).count();
                assert_eq!(differ, 0, "{preset} {w}×{h}, press at {centre:?}");
            }
        }
    }
}
