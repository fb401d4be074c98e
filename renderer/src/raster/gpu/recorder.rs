//! GPU work as a list, and the buffers it runs on.
//!
//! [`Work`] collects dispatches, clears and copies; only at [`Work::submit`] does it
//! know every dispatch's parameters, write them all into one uniform buffer and encode the list
//! (consecutive dispatches share one compute pass; wgpu orders their buffer accesses). So a frame
//! costs one small upload of parameters per submission rather than one buffer per dispatch.
//!
//! A [`Pool`] keeps the rasterizer's buffers between frames: a buffer is reallocated only when a
//! frame needs more than it holds, then to the next power of two (within the device's cap), so a
//! stream of similar frames allocates nothing after the first.

use std::collections::HashMap;

use wgpu::util::DeviceExt;

use c4g_scene::SceneError;

use super::device::{Gpu, Grid};
use super::kernels::{Kernel, Kernels};

enum Op<'k> {
    Dispatch {
        kernel: &'k Kernel,
        buffers: Vec<wgpu::Buffer>,
        params: std::ops::Range<u64>,
        grid: Grid,
    },
    Clear {
        buffer: wgpu::Buffer,
        size: u64,
    },
    Copy {
        from: wgpu::Buffer,
        to: wgpu::Buffer,
        to_offset: u64,
        size: u64,
    },
}

/// GPU work waiting to be submitted, with the device, kernels and buffers it runs on.
pub(super) struct Work<'k> {
    pub gpu: &'k Gpu,
    pub kernels: &'k Kernels,
    pool: &'k mut Pool,
    ops: Vec<Op<'k>>,
    params: Vec<u8>,
}

impl<'k> Work<'k> {
    pub fn new(gpu: &'k Gpu, kernels: &'k Kernels, pool: &'k mut Pool) -> Self {
        Self {
            gpu,
            kernels,
            pool,
            ops: Vec::new(),
            params: Vec::new(),
        }
    }

    /// Pooled buffer `name` (number `index` of that name) holding at least `bytes`.
    pub fn buffer(
        &mut self,
        name: &'static str,
        index: usize,
        bytes: u64,
        usage: Use,
    ) -> Result<wgpu::Buffer, SceneError> {
        self.pool.get(self.gpu, name, index, bytes, usage)
    }

    /// Runs `kernel` on `grid` with uniform `params` and `buffers` in the kernel's binding order.
    pub fn dispatch(
        &mut self,
        kernel: &'k Kernel,
        params: &[u32],
        buffers: &[&wgpu::Buffer],
        grid: Grid,
    ) {
        debug_assert_eq!(buffers.len(), kernel.storage.len(), "{}", kernel.name);
        let start = self.params.len() as u64;
        self.params
            .extend(params.iter().flat_map(|word| word.to_le_bytes()));
        let end = self.params.len() as u64;
        let align = self.gpu.uniform_align.max(16);
        let padded = end.div_ceil(align) * align;
        self.params.resize(padded as usize, 0);
        self.ops.push(Op::Dispatch {
            kernel,
            buffers: buffers.iter().map(|&b| b.clone()).collect(),
            params: start..end,
            grid,
        });
    }

    /// Zeroes the first `size` bytes of `buffer`.
    pub fn clear(&mut self, buffer: &wgpu::Buffer, size: u64) {
        if size > 0 {
            self.ops.push(Op::Clear {
                buffer: buffer.clone(),
                size,
            });
        }
    }

    /// Copies the first `size` bytes of `from` to `to` at `to_offset`.
    pub fn copy(&mut self, from: &wgpu::Buffer, to: &wgpu::Buffer, to_offset: u64, size: u64) {
        if size > 0 {
            self.ops.push(Op::Copy {
                from: from.clone(),
                to: to.clone(),
                to_offset,
                size,
            });
        }
    }

    /// Encodes and submits everything recorded so far.
    pub fn submit(&mut self) {
        if self.ops.is_empty() {
            return;
        }
        let gpu = self.gpu;
        let ops = std::mem::take(&mut self.ops);
        let params = std::mem::take(&mut self.params);
        let uniforms = (!params.is_empty()).then(|| {
            gpu.device
                .create_buffer_init(&wgpu::util::BufferInitDescriptor {
                    label: Some("c4g dispatch parameters"),
                    contents: &params,
                    usage: wgpu::BufferUsages::UNIFORM,
                })
        });
        let mut encoder = gpu
            .device
            .create_command_encoder(&wgpu::CommandEncoderDescriptor {
                label: Some("c4g frame"),
            });
        let mut ops = ops.iter().peekable();
        while let Some(op) = ops.next() {
            match op {
                Op::Dispatch { .. } => {
                    let mut pass = encoder.begin_compute_pass(&wgpu::ComputePassDescriptor {
                        label: Some("c4g kernels"),
                        timestamp_writes: None,
                    });
                    let mut next = Some(op);
                    while let Some(Op::Dispatch {
                        kernel,
                        buffers,
                        params,
                        grid,
                    }) = next
                    {
                        if let Some(uniforms) = &uniforms {
                            let group = bind_group(gpu, kernel, uniforms, params, buffers);
                            pass.set_pipeline(&kernel.pipeline);
                            pass.set_bind_group(0, &group, &[]);
                            pass.dispatch_workgroups(grid.x, grid.y, 1);
                        }
                        next = ops.next_if(|op| matches!(op, Op::Dispatch { .. }));
                    }
                }
                Op::Clear { buffer, size } => encoder.clear_buffer(buffer, 0, Some(*size)),
                Op::Copy {
                    from,
                    to,
                    to_offset,
                    size,
                } => encoder.copy_buffer_to_buffer(from, 0, to, *to_offset, *size),
            }
        }
        gpu.queue.submit([encoder.finish()]);
    }

    /// Submits everything recorded, then copies `sources` (each `(buffer, bytes)`) back to the host
    /// and hands `read` their bytes, one slice per source.
    pub fn read<T>(
        &mut self,
        sources: &[(&wgpu::Buffer, u64)],
        read: impl FnOnce(&[&[u8]]) -> T,
    ) -> Result<T, SceneError> {
        let total: u64 = sources
            .iter()
            .map(|(_, bytes)| bytes.next_multiple_of(16))
            .sum();
        let staging = self.buffer("read-back", 0, total, Use::ReadBack)?;
        let mut at = 0;
        let mut spans = Vec::with_capacity(sources.len());
        for &(buffer, bytes) in sources {
            self.copy(buffer, &staging, at, bytes);
            spans.push(at as usize..(at + bytes) as usize);
            at += bytes.next_multiple_of(16);
        }
        self.submit();
        self.gpu.read_mapped(&staging, total.max(16), |bytes| {
            let slices: Vec<&[u8]> = spans.iter().map(|span| &bytes[span.clone()]).collect();
            read(&slices)
        })
    }
}

fn bind_group(
    gpu: &Gpu,
    kernel: &Kernel,
    uniforms: &wgpu::Buffer,
    params: &std::ops::Range<u64>,
    buffers: &[wgpu::Buffer],
) -> wgpu::BindGroup {
    let mut entries = vec![wgpu::BindGroupEntry {
        binding: 0,
        resource: wgpu::BindingResource::Buffer(wgpu::BufferBinding {
            buffer: uniforms,
            offset: params.start,
            size: wgpu::BufferSize::new(params.end - params.start),
        }),
    }];
    for (&binding, buffer) in kernel.storage.iter().zip(buffers) {
        entries.push(wgpu::BindGroupEntry {
            binding,
            resource: buffer.as_entire_binding(),
        });
    }
    gpu.device.create_bind_group(&wgpu::BindGroupDescriptor {
        label: Some(kernel.name),
        layout: &kernel.layout,
        entries: &entries,
    })
}

/// What a pooled buffer is for.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(super) enum Use {
    /// Read and written by kernels, filled by uploads, copied out for read-back.
    Storage,
    /// The host reads it back.
    ReadBack,
}

/// The rasterizer's buffers, kept between frames by name.
#[derive(Default)]
pub(super) struct Pool {
    buffers: HashMap<(&'static str, usize), wgpu::Buffer>,
}

impl Pool {
    /// Buffer `name` (number `index` of that name) holding at least `bytes`.
    pub fn get(
        &mut self,
        gpu: &Gpu,
        name: &'static str,
        index: usize,
        bytes: u64,
        usage: Use,
    ) -> Result<wgpu::Buffer, SceneError> {
        let bytes = bytes.max(16).next_multiple_of(16);
        if bytes > gpu.buffer_cap {
            return Err(SceneError::Gpu(format!(
                "buffer {name} needs {bytes} bytes, more than the {} this device binds",
                gpu.buffer_cap
            )));
        }
        if let Some(buffer) = self.buffers.get(&(name, index))
            && buffer.size() >= bytes
        {
            return Ok(buffer.clone());
        }
        let size = bytes.next_power_of_two().min(gpu.buffer_cap);
        let usage = match usage {
            Use::Storage => {
                wgpu::BufferUsages::STORAGE
                    | wgpu::BufferUsages::COPY_DST
                    | wgpu::BufferUsages::COPY_SRC
            }
            Use::ReadBack => wgpu::BufferUsages::MAP_READ | wgpu::BufferUsages::COPY_DST,
        };
        // Drop the old one first: at the cap, two may not fit.
        self.buffers.remove(&(name, index));
        let buffer = gpu.device.create_buffer(&wgpu::BufferDescriptor {
            label: Some(name),
            size,
            usage,
            mapped_at_creation: false,
        });
        self.buffers.insert((name, index), buffer.clone());
        Ok(buffer)
    }

    /// Forgets every buffer (after a failed frame, whose buffers may be in any state).
    pub fn clear(&mut self) {
        self.buffers.clear();
    }
}
