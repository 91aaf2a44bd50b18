//! Present pass (`present.wgsl`): scale the offscreen frame into a window surface. The frame is
//! always rendered offscreen first, so PNG snapshots, tests and the window see the same image.

/// Pipeline and binding for one (offscreen texture, surface format) pair.
pub struct PresentPass {
    pipeline: wgpu::RenderPipeline,
    bind_group: wgpu::BindGroup,
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

impl PresentPass {
    /// Build for sampling `frame` (of `frame_size` pixels) into targets of `surface_format`.
    pub fn new(
        device: &wgpu::Device,
        frame: &wgpu::TextureView,
        frame_size: (u32, u32),
        surface_format: wgpu::TextureFormat,
    ) -> Self {
        let module = device.create_shader_module(wgpu::include_wgsl!("present.wgsl"));
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
                entry_point: Some("fs_main"),
                compilation_options: Default::default(),
                targets: &[Some(wgpu::ColorTargetState {
                    format: surface_format,
                    blend: None,
                    write_mask: wgpu::ColorWrites::ALL,
                })],
            }),
            multiview_mask: None,
            cache: None,
        });
        let sampler = device.create_sampler(&wgpu::SamplerDescriptor {
            label: Some("lungdyn present"),
            mag_filter: wgpu::FilterMode::Linear,
            min_filter: wgpu::FilterMode::Linear,
            ..Default::default()
        });
        let bind_group = device.create_bind_group(&wgpu::BindGroupDescriptor {
            label: Some("lungdyn present"),
            layout: &pipeline.get_bind_group_layout(0),
            entries: &[
                wgpu::BindGroupEntry {
                    binding: 0,
                    resource: wgpu::BindingResource::TextureView(frame),
                },
                wgpu::BindGroupEntry {
                    binding: 1,
                    resource: wgpu::BindingResource::Sampler(&sampler),
                },
            ],
        });
        Self {
            pipeline,
            bind_group,
            frame_size,
        }
    }

    /// Record the copy into `target` (of `target_size` pixels), the frame's aspect kept.
    pub fn encode(
        &self,
        encoder: &mut wgpu::CommandEncoder,
        target: &wgpu::TextureView,
        target_size: (u32, u32),
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
        pass.set_pipeline(&self.pipeline);
        pass.set_bind_group(0, &self.bind_group, &[]);
        pass.draw(0..3, 0..1);
    }
}

#[cfg(test)]
mod tests {
    use super::fit_viewport;

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
