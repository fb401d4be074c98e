//! The compute pipelines of the rasterizer, built once per device.
//!
//! Every kernel has an explicit bind group layout (binding 0 its uniform parameters, the rest
//! storage buffers in the order [`Recorder::dispatch`](super::recorder::Recorder::dispatch)
//! takes them), so a dispatch binds exactly the buffers its entry point uses and nothing else.

use c4g_scene::SceneError;

use super::device::Gpu;

/// How a kernel sees one binding.
#[derive(Debug, Clone, Copy)]
enum Access {
    Read,
    ReadWrite,
}

use Access::{Read, ReadWrite};

/// One compute entry point and the layout of its bindings.
pub(super) struct Kernel {
    pub name: &'static str,
    pub pipeline: wgpu::ComputePipeline,
    pub layout: wgpu::BindGroupLayout,
    /// Binding numbers of the storage buffers, in the order a dispatch passes them.
    pub storage: Vec<u32>,
}

/// Every kernel of a frame.
pub(super) struct Kernels {
    pub project: Kernel,
    pub scan_blocks: Kernel,
    pub add_block_sums: Kernel,
    pub histogram: Kernel,
    pub scatter: Kernel,
    pub count: Kernel,
    pub emit: Kernel,
    pub ranges: Kernel,
    pub blend_color: Kernel,
    pub blend_features: Kernel,
}

impl Kernels {
    pub fn new(gpu: &Gpu) -> Result<Self, SceneError> {
        gpu.scoped(|| {
            let project = module(gpu, "project", include_str!("project.wgsl"));
            let scan = module(gpu, "scan", include_str!("scan.wgsl"));
            let sort = module(gpu, "sort", include_str!("sort.wgsl"));
            let tiles = module(gpu, "tiles", include_str!("tiles.wgsl"));
            let blend_color = module(
                gpu,
                "blend color",
                concat!(include_str!("blend.wgsl"), include_str!("blend_color.wgsl")),
            );
            let blend_features = module(
                gpu,
                "blend features",
                concat!(
                    include_str!("blend.wgsl"),
                    include_str!("blend_features.wgsl")
                ),
            );
            let k = |module: &wgpu::ShaderModule, name, storage: &[(u32, Access)]| {
                kernel(gpu, module, name, storage)
            };
            Ok(Self {
                project: k(
                    &project,
                    "project",
                    &[
                        (1, Read),
                        (2, ReadWrite),
                        (3, ReadWrite),
                        (4, ReadWrite),
                        (5, ReadWrite),
                    ],
                ),
                scan_blocks: k(&scan, "scan_blocks", &[(1, ReadWrite), (2, ReadWrite)]),
                add_block_sums: k(&scan, "add_block_sums", &[(1, ReadWrite), (2, ReadWrite)]),
                histogram: k(&sort, "histogram", &[(1, Read), (2, ReadWrite)]),
                scatter: k(
                    &sort,
                    "scatter",
                    &[
                        (1, Read),
                        (3, Read),
                        (4, Read),
                        (5, ReadWrite),
                        (6, ReadWrite),
                    ],
                ),
                count: k(&tiles, "count", &[(1, Read), (2, Read), (3, ReadWrite)]),
                emit: k(
                    &tiles,
                    "emit",
                    &[
                        (1, Read),
                        (2, Read),
                        (4, Read),
                        (5, ReadWrite),
                        (6, ReadWrite),
                    ],
                ),
                ranges: k(&tiles, "ranges_of_tiles", &[(7, Read), (8, ReadWrite)]),
                blend_color: k(
                    &blend_color,
                    "blend_color",
                    &[
                        (1, Read),
                        (2, Read),
                        (3, Read),
                        (4, ReadWrite),
                        (5, ReadWrite),
                    ],
                ),
                blend_features: k(
                    &blend_features,
                    "blend_features",
                    &[
                        (1, Read),
                        (2, Read),
                        (3, Read),
                        (4, ReadWrite),
                        (5, Read),
                        (6, ReadWrite),
                    ],
                ),
            })
        })
    }
}

fn module(gpu: &Gpu, name: &str, source: &str) -> wgpu::ShaderModule {
    gpu.device
        .create_shader_module(wgpu::ShaderModuleDescriptor {
            label: Some(name),
            source: wgpu::ShaderSource::Wgsl(source.into()),
        })
}

fn kernel(
    gpu: &Gpu,
    module: &wgpu::ShaderModule,
    name: &'static str,
    storage: &[(u32, Access)],
) -> Kernel {
    let buffer = |binding, ty| wgpu::BindGroupLayoutEntry {
        binding,
        visibility: wgpu::ShaderStages::COMPUTE,
        ty: wgpu::BindingType::Buffer {
            ty,
            has_dynamic_offset: false,
            min_binding_size: None,
        },
        count: None,
    };
    let mut entries = vec![buffer(0, wgpu::BufferBindingType::Uniform)];
    for &(binding, access) in storage {
        let read_only = matches!(access, Read);
        entries.push(buffer(
            binding,
            wgpu::BufferBindingType::Storage { read_only },
        ));
    }
    let layout = gpu
        .device
        .create_bind_group_layout(&wgpu::BindGroupLayoutDescriptor {
            label: Some(name),
            entries: &entries,
        });
    let pipeline_layout = gpu
        .device
        .create_pipeline_layout(&wgpu::PipelineLayoutDescriptor {
            label: Some(name),
            bind_group_layouts: &[Some(&layout)],
            immediate_size: 0,
        });
    let pipeline = gpu
        .device
        .create_compute_pipeline(&wgpu::ComputePipelineDescriptor {
            label: Some(name),
            layout: Some(&pipeline_layout),
            module,
            entry_point: Some(name),
            compilation_options: wgpu::PipelineCompilationOptions {
                // Every kernel writes workgroup memory before reading it.
                zero_initialize_workgroup_memory: false,
                ..Default::default()
            },
            cache: None,
        });
    Kernel {
        name,
        pipeline,
        layout,
        storage: storage.iter().map(|&(binding, _)| binding).collect(),
    }
}

#[cfg(test)]
mod tests {
    use super::super::super::{
        ALPHA_MAX, ALPHA_MIN, DISCRIMINANT_FLOOR_3DGS, EPS2D, SIGMA_EXTENT, TRANSMITTANCE_MIN,
    };

    /// The value of `const NAME: f32 = ...;` in `source` (a number or a quotient of two).
    fn constant(source: &str, name: &str) -> Option<f32> {
        let line = source
            .lines()
            .find(|l| l.starts_with(&format!("const {name}: f32 = ")))?;
        let value = line.split('=').nth(1)?.trim().trim_end_matches(';');
        let mut parts = value.split('/').map(|v| v.trim().parse::<f32>());
        let first = parts.next()?.ok()?;
        match parts.next() {
            Some(divisor) => Some(first / divisor.ok()?),
            None => Some(first),
        }
    }

    #[test]
    fn shaders_use_the_forward_model_s_constants() {
        let project = include_str!("project.wgsl");
        let blend = include_str!("blend.wgsl");
        assert_eq!(constant(project, "EPS2D"), Some(EPS2D));
        assert_eq!(constant(project, "SIGMA_EXTENT"), Some(SIGMA_EXTENT));
        assert_eq!(constant(project, "ALPHA_MIN"), Some(ALPHA_MIN));
        assert_eq!(
            constant(project, "DISCRIMINANT_FLOOR_3DGS"),
            Some(DISCRIMINANT_FLOOR_3DGS)
        );
        assert_eq!(constant(blend, "SIGMA_EXTENT"), Some(SIGMA_EXTENT));
        assert_eq!(constant(blend, "ALPHA_MAX"), Some(ALPHA_MAX));
        assert_eq!(constant(blend, "ALPHA_MIN"), Some(ALPHA_MIN));
        assert_eq!(
            constant(blend, "TRANSMITTANCE_MIN"),
            Some(TRANSMITTANCE_MIN)
        );
    }
}
