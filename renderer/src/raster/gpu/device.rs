//! Which GPU the rasterizer runs on, and the device it opens there.
//!
//! Adapter choice is a policy with one override: by default the fastest adapter wins (a discrete
//! GPU, then an integrated or virtual one, then a software one such as Mesa's lavapipe, which is
//! how machines without a GPU and CI run the same shaders); [`ADAPTER_ENV`] names another. The
//! device asks for the adapter's own limits rather than WebGPU's defaults: buffer sizes decide how
//! large a scene or image one pass can hold, and the rasterizer plans around whatever it gets.
//!
//! wgpu reports most failures through error scopes rather than return values; [`Gpu::scoped`]
//! turns whatever a block of GPU work raised into one [`SceneError::Gpu`].

use std::fmt;
use std::sync::mpsc;

use c4g_scene::SceneError;

/// Environment variable that picks the adapter: unset, `auto` or `any` for the fastest one;
/// `hardware` (or `gpu`) for a hardware GPU only; `lavapipe`, `llvmpipe`, `software` or `cpu`
/// for a software adapter only; anything else for the first adapter whose name contains it
/// (case-insensitive). `WGPU_BACKEND` (wgpu's own, e.g. `vulkan`) narrows the backends searched.
pub const ADAPTER_ENV: &str = "C4G_WGPU_ADAPTER";

/// Which adapter to open.
#[derive(Debug, Clone, PartialEq, Eq, Default)]
pub enum AdapterChoice {
    /// The fastest adapter there is: discrete, integrated, virtual, other, then software.
    #[default]
    Auto,
    /// A hardware GPU only.
    Hardware,
    /// A software (CPU) adapter only, such as Mesa's lavapipe.
    Software,
    /// The first adapter, by the ranking of `Auto`, whose name contains this (case-insensitive).
    Named(String),
}

impl AdapterChoice {
    /// Reads a choice in the syntax of [`ADAPTER_ENV`].
    pub fn parse(text: &str) -> Self {
        let text = text.trim();
        match text.to_ascii_lowercase().as_str() {
            "" | "auto" | "any" => Self::Auto,
            "hardware" | "gpu" => Self::Hardware,
            "lavapipe" | "llvmpipe" | "software" | "cpu" => Self::Software,
            _ => Self::Named(text.to_owned()),
        }
    }

    /// The choice [`ADAPTER_ENV`] states, `Auto` when it is unset.
    pub fn from_env() -> Self {
        std::env::var(ADAPTER_ENV).map_or(Self::Auto, |v| Self::parse(&v))
    }

    fn admits(&self, info: &wgpu::AdapterInfo) -> bool {
        let software = info.device_type == wgpu::DeviceType::Cpu;
        match self {
            Self::Auto => true,
            Self::Hardware => !software,
            Self::Software => software,
            Self::Named(name) => info.name.to_lowercase().contains(&name.to_lowercase()),
        }
    }
}

impl fmt::Display for AdapterChoice {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Self::Auto => f.write_str("auto"),
            Self::Hardware => f.write_str("hardware"),
            Self::Software => f.write_str("software"),
            Self::Named(name) => write!(f, "named {name:?}"),
        }
    }
}

/// The adapter a rasterizer runs on, in words.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct AdapterDescription {
    /// The adapter's name, e.g. `llvmpipe (LLVM 15.0.6, 256 bits)`.
    pub name: String,
    /// The graphics API wgpu drives it with (`Vulkan`, `Metal`, `Dx12`).
    pub backend: String,
    /// `DiscreteGpu`, `IntegratedGpu`, `VirtualGpu`, `Cpu` or `Other`.
    pub device_type: String,
    /// Driver name and version, as the driver reports them.
    pub driver: String,
    /// True for an adapter that runs on the CPU (lavapipe, WARP, SwiftShader).
    pub software: bool,
}

impl fmt::Display for AdapterDescription {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(
            f,
            "{} ({}, {}, driver {})",
            self.name, self.backend, self.device_type, self.driver
        )
    }
}

impl From<&wgpu::AdapterInfo> for AdapterDescription {
    fn from(info: &wgpu::AdapterInfo) -> Self {
        Self {
            name: info.name.clone(),
            backend: format!("{:?}", info.backend),
            device_type: format!("{:?}", info.device_type),
            driver: format!("{} {}", info.driver, info.driver_info)
                .trim()
                .to_owned(),
            software: info.device_type == wgpu::DeviceType::Cpu,
        }
    }
}

/// An open device and what the rasterizer needs to know about it.
pub(super) struct Gpu {
    pub device: wgpu::Device,
    pub queue: wgpu::Queue,
    pub adapter: AdapterDescription,
    /// Largest storage buffer one binding (and so one buffer of ours) may hold, in bytes.
    pub buffer_cap: u64,
    /// Largest workgroup count along one dispatch dimension.
    pub max_groups: u32,
    /// Alignment of uniform buffer offsets.
    pub uniform_align: u64,
}

/// A dispatch size: `x · y ≥` the workgroups wanted; shaders fold `(x, y)` back into one index.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(super) struct Grid {
    pub x: u32,
    pub y: u32,
}

/// Workgroup storage and invocations the shaders need.
const NEEDED_WORKGROUP_STORAGE: u32 = 3 * 256 * 16 + 64;
const NEEDED_INVOCATIONS: u32 = 256;
const NEEDED_STORAGE_BUFFERS: u32 = 7;

impl Gpu {
    /// Opens the adapter `choice` names; `buffer_limit` lowers the buffer cap below the device's.
    pub fn open(choice: &AdapterChoice, buffer_limit: Option<u64>) -> Result<Self, SceneError> {
        let backends = wgpu::Backends::PRIMARY.with_env();
        let instance = wgpu::Instance::new(wgpu::InstanceDescriptor {
            backends,
            ..wgpu::InstanceDescriptor::new_without_display_handle()
        });
        let mut adapters = pollster::block_on(instance.enumerate_adapters(backends));
        let found: Vec<String> = adapters
            .iter()
            .map(|a| AdapterDescription::from(&a.get_info()).to_string())
            .collect();
        adapters.retain(|a| choice.admits(&a.get_info()) && can_run_the_shaders(a));
        adapters.sort_by_key(|a| rank(&a.get_info()));
        let Some(adapter) = adapters.into_iter().next() else {
            let seen = if found.is_empty() {
                "wgpu found no adapter (no GPU driver and no software Vulkan such as Mesa's \
                 lavapipe: install mesa-vulkan-drivers)"
                    .to_owned()
            } else {
                format!("found {}", found.join("; "))
            };
            return Err(SceneError::GpuUnavailable(format!(
                "none matches {ADAPTER_ENV}={choice} with compute support: {seen}"
            )));
        };

        let info = adapter.get_info();
        let limits = adapter.limits();
        let (device, queue) = pollster::block_on(adapter.request_device(&wgpu::DeviceDescriptor {
            label: Some("c4g rasterizer"),
            required_limits: limits.clone(),
            ..Default::default()
        }))
        .map_err(|e| SceneError::Gpu(format!("cannot open {}: {e}", info.name)))?;

        let device_cap = limits
            .max_storage_buffer_binding_size
            .min(limits.max_buffer_size);
        // Keep the cap a multiple of 16 so vec4 arrays fill it exactly.
        let buffer_cap = buffer_limit.map_or(device_cap, |l| l.min(device_cap)) & !15;
        Ok(Self {
            device,
            queue,
            adapter: AdapterDescription::from(&info),
            buffer_cap,
            max_groups: limits.max_compute_workgroups_per_dimension,
            uniform_align: u64::from(limits.min_uniform_buffer_offset_alignment),
        })
    }

    /// A grid of at least `workgroups` workgroups, folded into 2D past the per-dimension limit.
    pub fn grid(&self, workgroups: u32) -> Result<Grid, SceneError> {
        fold_grid(workgroups, self.max_groups).ok_or_else(|| {
            SceneError::Gpu(format!(
                "{workgroups} workgroups exceed the device's {0}×{0} grid",
                self.max_groups
            ))
        })
    }

    /// Runs `work` with error scopes around it: any validation, out-of-memory or internal error it
    /// raised becomes the result (it explains a failure of `work` better than `work` can).
    pub fn scoped<T>(&self, work: impl FnOnce() -> Result<T, SceneError>) -> Result<T, SceneError> {
        let internal = self.device.push_error_scope(wgpu::ErrorFilter::Internal);
        let memory = self.device.push_error_scope(wgpu::ErrorFilter::OutOfMemory);
        let validation = self.device.push_error_scope(wgpu::ErrorFilter::Validation);
        let result = work();
        let errors = [
            pollster::block_on(validation.pop()),
            pollster::block_on(memory.pop()),
            pollster::block_on(internal.pop()),
        ];
        match errors.into_iter().flatten().next() {
            Some(error) => Err(SceneError::Gpu(error.to_string())),
            None => result,
        }
    }

    /// Waits for the queue to finish what was submitted.
    pub fn wait(&self) -> Result<(), SceneError> {
        self.device
            .poll(wgpu::PollType::wait_indefinitely())
            .map(|_| ())
            .map_err(|e| SceneError::Gpu(format!("waiting for the GPU: {e}")))
    }

    /// Maps `buffer[..size]` (a MAP_READ buffer whose copies were submitted) and hands its bytes
    /// to `read`.
    pub fn read_mapped<T>(
        &self,
        buffer: &wgpu::Buffer,
        size: u64,
        read: impl FnOnce(&[u8]) -> T,
    ) -> Result<T, SceneError> {
        let (sender, receiver) = mpsc::channel();
        buffer.map_async(wgpu::MapMode::Read, ..size, move |result| {
            // The receiver outlives this callback: it waits below.
            let _ = sender.send(result);
        });
        self.wait()?;
        receiver
            .recv()
            .map_err(|e| SceneError::Gpu(format!("read-back never completed: {e}")))?
            .map_err(|e| SceneError::Gpu(format!("cannot map a read-back buffer: {e}")))?;
        let value = {
            let view = buffer
                .get_mapped_range(..size)
                .map_err(|e| SceneError::Gpu(format!("cannot view a read-back buffer: {e}")))?;
            read(&view)
        };
        buffer.unmap();
        Ok(value)
    }
}

/// At least `workgroups` (and at least one) workgroups as `x · y`, each at most `max_groups`.
fn fold_grid(workgroups: u32, max_groups: u32) -> Option<Grid> {
    let x = workgroups.clamp(1, max_groups);
    let y = workgroups.div_ceil(x).max(1);
    (y <= max_groups).then_some(Grid { x, y })
}

/// Sort key of an adapter: hardware before software, discrete first.
fn rank(info: &wgpu::AdapterInfo) -> u8 {
    match info.device_type {
        wgpu::DeviceType::DiscreteGpu => 0,
        wgpu::DeviceType::IntegratedGpu => 1,
        wgpu::DeviceType::VirtualGpu => 2,
        wgpu::DeviceType::Other => 3,
        wgpu::DeviceType::Cpu => 4,
    }
}

fn can_run_the_shaders(adapter: &wgpu::Adapter) -> bool {
    let limits = adapter.limits();
    adapter
        .get_downlevel_capabilities()
        .flags
        .contains(wgpu::DownlevelFlags::COMPUTE_SHADERS)
        && limits.max_compute_workgroup_storage_size >= NEEDED_WORKGROUP_STORAGE
        && limits.max_compute_invocations_per_workgroup >= NEEDED_INVOCATIONS
        && limits.max_storage_buffers_per_shader_stage >= NEEDED_STORAGE_BUFFERS
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn adapter_choices_parse_from_their_names() {
        assert_eq!(AdapterChoice::parse(""), AdapterChoice::Auto);
        assert_eq!(AdapterChoice::parse("Any"), AdapterChoice::Auto);
        assert_eq!(AdapterChoice::parse("lavapipe"), AdapterChoice::Software);
        assert_eq!(AdapterChoice::parse("CPU"), AdapterChoice::Software);
        assert_eq!(AdapterChoice::parse("gpu"), AdapterChoice::Hardware);
        assert_eq!(
            AdapterChoice::parse(" RTX 4090 "),
            AdapterChoice::Named("RTX 4090".to_owned())
        );
    }

    #[test]
    fn grids_fold_into_two_dimensions_past_the_limit() {
        assert_eq!(fold_grid(10, 65535), Some(Grid { x: 10, y: 1 }));
        assert_eq!(fold_grid(65536, 65535), Some(Grid { x: 65535, y: 2 }));
        assert_eq!(fold_grid(0, 65535), Some(Grid { x: 1, y: 1 }));
        assert_eq!(fold_grid(u32::MAX, 16), None);
    }
}
