//! Present pass (`present.wgsl`): scale the offscreen frame into a window surface. The frame is
//! always rendered offscreen first, so PNG snapshots, tests and the window see the same image.

/// Pipelines and bindings for one (offscreen texture, surface format) pair: a filtered scaling
/// copy, and a texel-for-texel one used when the target is exactly the frame's size.
pub struct PresentPass {
    scaled: (wgpu::RenderPipeline, wgpu::BindGroup),
    exact: (wgpu::RenderPipeline, wgpu::BindGroup),
    /// The format the target is viewed in for the exact copy (the surface's, or its plain-bytes
    /// twin when the frame's bytes view is given).
    exact_format: wgpu::TextureFormat,
    surface_format: wgpu::TextureFormat,
    frame_size: (u32, u32),
}

/// The viewport `(x, y, width, height)` that shows a `frame`-sized image as large as fits in a
/// `target`-sized surface without changing its aspect, centred (black bars on the other axis).
pub fn fit_viewport(frame: (u32, u32), target: (u32, u32)) -> (f32, f32, f32, f32) {
    let (fw, fh) = (frame.0.max(1) as f64, frame.1.max(1) as f64);
    let (tw, th) = (target.0.max(1) as f64, target.1.max(1) as f64);
    let scale = (tw / fw).min(th / fh);
    let (w, h) = ((fw * scale).round(), (fh * scale).round());
    (
        ((tw - w) / 2.0).floor() as f32,
        ((th - h) / 2.0).floor() as f32,
        w as f32,
        h as f32,
    )
}

/// The surface format to present in: `default` (wgpu's choice, the surface's first) if it is sRGB,
/// else its sRGB twin or any sRGB format the surface offers, else `default` — the frame is sRGB, and
/// a filtered copy into a UNORM surface would write linear light and show it too dark.
pub fn surface_format(
    offered: &[wgpu::TextureFormat],
    default: wgpu::TextureFormat,
) -> wgpu::TextureFormat {
    if default.is_srgb() {
        return default;
    }
    let twin = default.add_srgb_suffix();
    if offered.contains(&twin) {
        return twin;
    }
    offered
        .iter()
        .copied()
        .find(|f| f.is_srgb())
        .unwrap_or(default)
}

impl PresentPass {
    /// Build for sampling `frame` (of `frame_size` pixels) into targets of `surface_format`.
    /// With `frame_bytes` (the same frame viewed without sRGB, [`crate::Renderer::color_bytes_view`])
    /// a target of the frame's size is written through a plain-bytes view of it, in
    /// [`Self::view_format`] (so its surface must list that view format): the bytes are copied
    /// with no sRGB decode and re-encode per pixel. Without it (an OpenXR swapchain, which offers
    /// no such view) the exact copy reads and writes sRGB.
    pub fn new(
        device: &wgpu::Device,
        frame: &wgpu::TextureView,
        frame_bytes: Option<&wgpu::TextureView>,
        frame_size: (u32, u32),
        surface_format: wgpu::TextureFormat,
    ) -> Self {
        let module = device.create_shader_module(wgpu::include_wgsl!("present.wgsl"));
        let sampler = device.create_sampler(&wgpu::SamplerDescriptor {
            label: Some("lungdyn present"),
            mag_filter: wgpu::FilterMode::Linear,
            min_filter: wgpu::FilterMode::Linear,
            ..Default::default()
        });
        // Each pipeline with the layout its fragment entry point implies (the exact copy binds
        // no sampler) and its own bind group.
        let build =
            |entry: &str, frame: &wgpu::TextureView, format: wgpu::TextureFormat, sampled: bool| {
                let pipeline = device.create_render_pipeline(&wgpu::RenderPipelineDescriptor {
                    label: Some("lungdyn present"),
                    layout: None,
                    vertex: wgpu::VertexState {
                        module: &module,
                        entry_point: Some("vs_main"),
                        compilation_options: Default::default(),
                        buffers: &[],
                    },
                    primitive: Default::default(),
                    depth_stencil: None,
                    multisample: Default::default(),
                    fragment: Some(wgpu::FragmentState {
                        module: &module,
                        entry_point: Some(entry),
                        compilation_options: Default::default(),
                        targets: &[Some(wgpu::ColorTargetState {
                            format,
                            blend: None,
                            write_mask: wgpu::ColorWrites::ALL,
                        })],
                    }),
                    multiview_mask: None,
                    cache: None,
                });
                let mut entries = vec![wgpu::BindGroupEntry {
                    binding: 0,
                    resource: wgpu::BindingResource::TextureView(frame),
                }];
                if sampled {
                    entries.push(wgpu::BindGroupEntry {
                        binding: 1,
                        resource: wgpu::BindingResource::Sampler(&sampler),
                    });
                }
                let bind_group = device.create_bind_group(&wgpu::BindGroupDescriptor {
                    label: Some("lungdyn present"),
                    layout: &pipeline.get_bind_group_layout(0),
                    entries: &entries,
                });
                (pipeline, bind_group)
            };
        let (exact_frame, exact_format) = match frame_bytes {
            Some(bytes) => (bytes, surface_format.remove_srgb_suffix()),
            None => (frame, surface_format),
        };
        // Into a surface with no sRGB format, the filtered copy samples the frame's bytes too
        // (filtered in sRGB rather than linear light, but as bright as the frame).
        let scaled_frame = match frame_bytes {
            Some(bytes) if !surface_format.is_srgb() => bytes,
            _ => frame,
        };
        Self {
            scaled: build("fs_main", scaled_frame, surface_format, true),
            exact: build("fs_load", exact_frame, exact_format, false),
            exact_format,
            surface_format,
            frame_size,
        }
    }

    /// Whether a target of `target_size` gets the texel-for-texel copy (it is the frame's size).
    pub fn is_exact(&self, target_size: (u32, u32)) -> bool {
        target_size == self.frame_size
    }

    /// The format to view a target of `target_size` in for [`Self::encode`].
    pub fn view_format(&self, target_size: (u32, u32)) -> wgpu::TextureFormat {
        if self.is_exact(target_size) {
            self.exact_format
        } else {
            self.surface_format
        }
    }

    /// The view formats a surface of `surface_format` must be configured with for this pass.
    pub fn surface_view_formats(&self) -> Vec<wgpu::TextureFormat> {
        if self.exact_format == self.surface_format {
            Vec::new()
        } else {
            vec![self.exact_format]
        }
    }

    /// Record the copy into `target` (of `target_size` pixels, viewed in
    /// [`Self::view_format`]), the frame's aspect kept.
    pub fn encode(
        &self,
        encoder: &mut wgpu::CommandEncoder,
        target: &wgpu::TextureView,
        target_size: (u32, u32),
    ) {
        let exact = self.is_exact(target_size);
        self.encode_with(encoder, target, target_size, exact);
    }

    /// The filtered copy whatever the size (the target viewed in the surface's own format): what
    /// a frame of the window's size cost before the exact copy, for `examples/present_floor.rs`.
    pub fn encode_filtered(
        &self,
        encoder: &mut wgpu::CommandEncoder,
        target: &wgpu::TextureView,
        target_size: (u32, u32),
    ) {
        self.encode_with(encoder, target, target_size, false);
    }

    fn encode_with(
        &self,
        encoder: &mut wgpu::CommandEncoder,
        target: &wgpu::TextureView,
        target_size: (u32, u32),
        exact: bool,
    ) {
        let mut pass = encoder.begin_render_pass(&wgpu::RenderPassDescriptor {
            label: Some("lungdyn present"),
            color_attachments: &[Some(wgpu::RenderPassColorAttachment {
                view: target,
                depth_slice: None,
                resolve_target: None,
                ops: wgpu::Operations {
                    load: wgpu::LoadOp::Clear(wgpu::Color::BLACK),
                    store: wgpu::StoreOp::Store,
                },
            })],
            depth_stencil_attachment: None,
            timestamp_writes: None,
            occlusion_query_set: None,
            multiview_mask: None,
        });
        let (x, y, w, h) = fit_viewport(self.frame_size, target_size);
        pass.set_viewport(x, y, w, h, 0.0, 1.0);
        let (pipeline, bind_group) = if exact { &self.exact } else { &self.scaled };
        pass.set_pipeline(pipeline);
        pass.set_bind_group(0, bind_group, &[]);
        pass.draw(0..3, 0..1);
    }
}

#[cfg(test)]
mod tests {
    use super::{fit_viewport, PresentPass};

    /// Present `frame` (RGBA sRGB bytes, `w` × `h`) into a BGRA sRGB target of `target` size
    /// through a pass with or without the frame's plain-bytes view; the target's bytes as RGBA.
    fn present(
        gpu: &crate::gpu::Gpu,
        frame: &[u8],
        (w, h): (u32, u32),
        target: (u32, u32),
        bytes_view: bool,
    ) -> Vec<u8> {
        let d = &gpu.device;
        let extent = |(width, height)| wgpu::Extent3d {
            width,
            height,
            depth_or_array_layers: 1,
        };
        let srgb = crate::draw::COLOR_FORMAT;
        let texture = d.create_texture(&wgpu::TextureDescriptor {
            label: None,
            size: extent((w, h)),
            mip_level_count: 1,
            sample_count: 1,
            dimension: wgpu::TextureDimension::D2,
            format: srgb,
            usage: wgpu::TextureUsages::TEXTURE_BINDING | wgpu::TextureUsages::COPY_DST,
            view_formats: &[srgb.remove_srgb_suffix()],
        });
        gpu.queue.write_texture(
            texture.as_image_copy(),
            frame,
            wgpu::TexelCopyBufferLayout {
                offset: 0,
                bytes_per_row: Some(w * 4),
                rows_per_image: None,
            },
            extent((w, h)),
        );
        let view = texture.create_view(&Default::default());
        let bytes = texture.create_view(&wgpu::TextureViewDescriptor {
            format: Some(srgb.remove_srgb_suffix()),
            ..Default::default()
        });
        let surface_format = wgpu::TextureFormat::Bgra8UnormSrgb;
        let pass = PresentPass::new(
            d,
            &view,
            bytes_view.then_some(&bytes),
            (w, h),
            surface_format,
        );
        let out = d.create_texture(&wgpu::TextureDescriptor {
            label: None,
            size: extent(target),
            mip_level_count: 1,
            sample_count: 1,
            dimension: wgpu::TextureDimension::D2,
            format: surface_format,
            usage: wgpu::TextureUsages::RENDER_ATTACHMENT | wgpu::TextureUsages::COPY_SRC,
            view_formats: &pass.surface_view_formats(),
        });
        let out_view = out.create_view(&wgpu::TextureViewDescriptor {
            format: Some(pass.view_format(target)),
            ..Default::default()
        });
        let row = (target.0 * 4).div_ceil(wgpu::COPY_BYTES_PER_ROW_ALIGNMENT)
            * wgpu::COPY_BYTES_PER_ROW_ALIGNMENT;
        let buffer = d.create_buffer(&wgpu::BufferDescriptor {
            label: None,
            size: (row * target.1) as u64,
            usage: wgpu::BufferUsages::COPY_DST | wgpu::BufferUsages::MAP_READ,
            mapped_at_creation: false,
        });
        let mut encoder = d.create_command_encoder(&Default::default());
        pass.encode(&mut encoder, &out_view, target);
        encoder.copy_texture_to_buffer(
            out.as_image_copy(),
            wgpu::TexelCopyBufferInfo {
                buffer: &buffer,
                layout: wgpu::TexelCopyBufferLayout {
                    offset: 0,
                    bytes_per_row: Some(row),
                    rows_per_image: None,
                },
            },
            extent(target),
        );
        gpu.queue.submit([encoder.finish()]);
        crate::read_mapped(gpu, &buffer, |b| {
            b.chunks(row as usize)
                .flat_map(|r| r[..target.0 as usize * 4].chunks(4))
                .flat_map(|p| [p[2], p[1], p[0], p[3]])
                .collect()
        })
        .expect("the target reads back")
    }

    /// A window of the frame's size gets the frame's bytes exactly — through the plain-bytes views
    /// (the window's path) with no sRGB decode and re-encode, and through sRGB views (an OpenXR
    /// swapchain's) within one step of 255 — and a larger window a scaled frame.
    #[test]
    fn a_window_of_the_frames_size_gets_its_bytes_exactly() {
        let Some(gpu) = crate::gpu::Gpu::for_tests() else {
            return;
        };
        let (w, h) = (67, 41);
        // Every byte value in every channel, at pixels no filter would leave alone.
        let frame: Vec<u8> = (0..w * h * 4)
            .map(|i| ((i * 97 + i / 4 * 13) % 256) as u8)
            .collect();
        let exact = present(&gpu, &frame, (w, h), (w, h), true);
        assert!(exact == frame, "the plain-bytes copy changed bytes");
        let srgb = present(&gpu, &frame, (w, h), (w, h), false);
        let worst = srgb
            .iter()
            .zip(&frame)
            .map(|(a, b)| a.abs_diff(*b))
            .max()
            .unwrap();
        assert!(worst <= 1, "the sRGB copy moved a byte by {worst}");
        let scaled = present(&gpu, &frame, (w, h), (2 * w, 2 * h), true);
        assert_eq!(scaled.len(), (4 * w * h * 4) as usize);
        // Filtering (in linear light) moves each pixel but not the picture's linear mean; a pass
        // that drew nothing would leave black, a mean of 0.
        let linear_mean = |b: &[u8]| {
            let lin = |v: u8| {
                let c = v as f64 / 255.0;
                if c <= 0.04045 {
                    c / 12.92
                } else {
                    ((c + 0.055) / 1.055).powf(2.4)
                }
            };
            let rgb: Vec<f64> = b
                .chunks(4)
                .flat_map(|p| p[..3].iter().map(|&v| lin(v)))
                .collect();
            rgb.iter().sum::<f64>() / rgb.len() as f64
        };
        let (m, s) = (linear_mean(&frame), linear_mean(&scaled));
        assert!(
            (m - s).abs() < 0.02 * m,
            "scaled linear mean {s} against the frame's {m}"
        );
    }

    /// An sRGB surface format is taken where the surface offers one, whatever it lists first.
    #[test]
    fn the_surface_is_presented_in_srgb_where_it_offers_it() {
        use super::surface_format;
        use wgpu::TextureFormat as F;
        let offered = [F::Bgra8Unorm, F::Bgra8UnormSrgb];
        assert_eq!(surface_format(&offered, F::Bgra8Unorm), F::Bgra8UnormSrgb);
        assert_eq!(
            surface_format(&offered, F::Bgra8UnormSrgb),
            F::Bgra8UnormSrgb
        );
        let other = [F::Bgra8Unorm, F::Rgba8UnormSrgb];
        assert_eq!(surface_format(&other, F::Bgra8Unorm), F::Rgba8UnormSrgb);
        assert_eq!(
            surface_format(&[F::Bgra8Unorm], F::Bgra8Unorm),
            F::Bgra8Unorm
        );
    }

    #[test]
    fn a_frame_of_the_targets_size_fills_it() {
        assert_eq!(
            fit_viewport((1280, 720), (1280, 720)),
            (0.0, 0.0, 1280.0, 720.0)
        );
        assert_eq!(
            fit_viewport((640, 360), (1280, 720)),
            (0.0, 0.0, 1280.0, 720.0)
        );
    }

    #[test]
    fn another_aspect_is_letterboxed_never_stretched() {
        // Two 4:3 eyes (1600x600) on a 16:9 display: bars above and below.
        let (x, y, w, h) = fit_viewport((1600, 600), (1920, 1080));
        assert_eq!((x, w), (0.0, 1920.0));
        assert_eq!(h, 720.0);
        assert_eq!(y, 180.0);
        // A tall frame on a wide display: bars left and right.
        let (x, y, w, h) = fit_viewport((600, 800), (1920, 1080));
        assert_eq!((y, h), (0.0, 1080.0));
        assert_eq!(w, 810.0);
        assert_eq!(x, 555.0);
        // Degenerate sizes never divide by zero.
        let v = fit_viewport((0, 0), (0, 0));
        assert!(v.0.is_finite() && v.2 >= 1.0 && v.3 >= 1.0);
    }
}
