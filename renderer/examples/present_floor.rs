//! The floor under any fullscreen frame rate on this machine: a borderless fullscreen window on the
//! primary display that draws nothing of the lungs, only what every frame of the renderer pays
//! besides drawing them, as fast as the surface takes frames.
//!
//! - `--mode clear`: acquire the surface image, clear it, present (the window system's and the
//!   driver's cost alone).
//! - `--mode present`: also clear an offscreen image of the display's size and scale it into the
//!   surface with the renderer's own present pass (`renderer::present::PresentPass`), as every
//!   windowed or fullscreen frame does after its lungs, HUD and resolve.
//!
//! `cargo run --release -p renderer --example present_floor -- --mode present --seconds 10` under
//! a display (`xvfb-run -a -s "-screen 0 1920x1080x24"` for a virtual one). It prints the frames,
//! the rate and the frame period's p50/p99/max. If the floor's rate is under 60 fps, no content
//! reaches 60 fps fullscreen on this machine (docs/DEPLOY.md).

use std::sync::Arc;
use std::time::{Duration, Instant};

use clap::{Parser, ValueEnum};
use renderer::gpu::Gpu;
use renderer::present::PresentPass;
use renderer::window::{choose_present_mode, PresentChoice};
use winit::application::ApplicationHandler;
use winit::dpi::PhysicalSize;
use winit::event::WindowEvent;
use winit::event_loop::{ActiveEventLoop, ControlFlow, EventLoop};
use winit::window::{Fullscreen, Window, WindowId};

#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum)]
enum CopyPath {
    /// Texel for texel through plain-bytes views of the frame and the surface (the window's path).
    Bytes,
    /// Texel for texel through sRGB views (an OpenXR swapchain's path).
    Srgb,
    /// A filtered sample per pixel (the pass before the exact copy; a scaled window's path).
    Filtered,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum)]
enum Mode {
    /// Clear the surface image and present it.
    Clear,
    /// Clear a display-sized offscreen image and scale it in with the renderer's present pass.
    Present,
}

/// Measure the fullscreen frame-rate floor: a frame that draws nothing.
#[derive(Debug, Parser)]
struct Args {
    /// What each frame does.
    #[arg(long, value_enum, default_value = "present")]
    mode: Mode,
    /// How long to run, seconds (the first second is not counted: start-up).
    #[arg(long, default_value_t = 10.0)]
    seconds: f64,
    /// With `--mode present`, how the frame is copied into the surface.
    #[arg(long, value_enum, default_value = "bytes")]
    copy: CopyPath,
    /// How to present (as `lungdyn demo --present-mode`).
    #[arg(long, value_enum, default_value = "latency")]
    present_mode: PresentChoice,
}

struct Open {
    window: Arc<Window>,
    gpu: Gpu,
    surface: wgpu::Surface<'static>,
    config: wgpu::SurfaceConfiguration,
    offscreen: Option<(wgpu::TextureView, PresentPass)>,
}

struct App {
    args: Args,
    open: Option<Open>,
    start: Option<Instant>,
    last: Option<Instant>,
    periods: Vec<Duration>,
    error: Option<String>,
}

impl App {
    fn open(&mut self, event_loop: &ActiveEventLoop) -> Result<(), String> {
        let monitor = event_loop
            .primary_monitor()
            .or_else(|| event_loop.available_monitors().next())
            .ok_or("no display: run under a display (xvfb-run -a for a virtual one)")?;
        let size = monitor.size();
        let window = Arc::new(
            event_loop
                .create_window(
                    Window::default_attributes()
                        .with_title("lungdyn present floor")
                        .with_fullscreen(Some(Fullscreen::Borderless(Some(monitor))))
                        .with_inner_size(PhysicalSize::new(size.width, size.height)),
                )
                .map_err(|e| format!("cannot open the window: {e}"))?,
        );
        let (gpu, surface) = Gpu::with_window(window.clone()).map_err(|e| e.to_string())?;
        let inner = window.inner_size();
        let mut config = surface
            .get_default_config(&gpu.adapter, inner.width.max(1), inner.height.max(1))
            .ok_or("the adapter cannot present to this window")?;
        let caps = surface.get_capabilities(&gpu.adapter);
        eprintln!(
            "present_floor: the surface offers formats {:?}, usages {:?}",
            caps.formats, caps.usages
        );
        config.present_mode =
            choose_present_mode(self.args.present_mode, false, &caps.present_modes)
                .map_err(|e| e.to_string())?;
        config.desired_maximum_frame_latency = 1;
        let offscreen = (self.args.mode == Mode::Present).then(|| {
            let texture = gpu.device.create_texture(&wgpu::TextureDescriptor {
                label: Some("present floor offscreen"),
                size: wgpu::Extent3d {
                    width: config.width,
                    height: config.height,
                    depth_or_array_layers: 1,
                },
                mip_level_count: 1,
                sample_count: 1,
                dimension: wgpu::TextureDimension::D2,
                format: renderer::draw::COLOR_FORMAT,
                usage: wgpu::TextureUsages::RENDER_ATTACHMENT
                    | wgpu::TextureUsages::TEXTURE_BINDING,
                view_formats: &[renderer::draw::COLOR_FORMAT.remove_srgb_suffix()],
            });
            let view = texture.create_view(&Default::default());
            let bytes = texture.create_view(&wgpu::TextureViewDescriptor {
                format: Some(renderer::draw::COLOR_FORMAT.remove_srgb_suffix()),
                ..Default::default()
            });
            let pass = PresentPass::new(
                &gpu.device,
                &view,
                (self.args.copy == CopyPath::Bytes).then_some(&bytes),
                (config.width, config.height),
                config.format,
            );
            (view, pass)
        });
        if let Some((_, pass)) = &offscreen {
            config.view_formats = pass.surface_view_formats();
        }
        surface.configure(&gpu.device, &config);
        eprintln!(
            "present_floor: {}x{} on {} ({:?}), {:?}, mode {:?}, copy {:?}, view formats {:?}",
            config.width,
            config.height,
            gpu.info.name,
            gpu.info.device_type,
            config.present_mode,
            self.args.mode,
            self.args.copy,
            config.view_formats
        );
        self.open = Some(Open {
            window,
            gpu,
            surface,
            config,
            offscreen,
        });
        Ok(())
    }

    fn frame(&mut self) {
        let Some(o) = self.open.as_ref() else { return };
        let image = match o.surface.get_current_texture() {
            wgpu::CurrentSurfaceTexture::Success(t)
            | wgpu::CurrentSurfaceTexture::Suboptimal(t) => t,
            wgpu::CurrentSurfaceTexture::Outdated | wgpu::CurrentSurfaceTexture::Lost => {
                o.surface.configure(&o.gpu.device, &o.config);
                return;
            }
            _ => return,
        };
        let size = (o.config.width, o.config.height);
        let filtered = self.args.copy == CopyPath::Filtered;
        let format = match &o.offscreen {
            Some((_, pass)) if !filtered => pass.view_format(size),
            _ => o.config.format,
        };
        let view = image.texture.create_view(&wgpu::TextureViewDescriptor {
            format: Some(format),
            ..Default::default()
        });
        let mut encoder = o.gpu.device.create_command_encoder(&Default::default());
        let clear = |encoder: &mut wgpu::CommandEncoder, target: &wgpu::TextureView| {
            encoder.begin_render_pass(&wgpu::RenderPassDescriptor {
                label: Some("present floor clear"),
                color_attachments: &[Some(wgpu::RenderPassColorAttachment {
                    view: target,
                    depth_slice: None,
                    resolve_target: None,
                    ops: wgpu::Operations {
                        load: wgpu::LoadOp::Clear(wgpu::Color {
                            r: 0.1,
                            g: 0.1,
                            b: 0.12,
                            a: 1.0,
                        }),
                        store: wgpu::StoreOp::Store,
                    },
                })],
                depth_stencil_attachment: None,
                timestamp_writes: None,
                occlusion_query_set: None,
                multiview_mask: None,
            });
        };
        match &o.offscreen {
            None => clear(&mut encoder, &view),
            Some((offscreen, pass)) => {
                clear(&mut encoder, offscreen);
                if filtered {
                    pass.encode_filtered(&mut encoder, &view, size);
                } else {
                    pass.encode(&mut encoder, &view, size);
                }
            }
        }
        o.gpu.queue.submit([encoder.finish()]);
        o.window.pre_present_notify();
        o.gpu.queue.present(image);
        let now = Instant::now();
        let start = *self.start.get_or_insert(now);
        if now - start > Duration::from_secs(1) {
            if let Some(last) = self.last {
                self.periods.push(now - last);
            }
        }
        self.last = Some(now);
    }
}

impl ApplicationHandler for App {
    fn resumed(&mut self, event_loop: &ActiveEventLoop) {
        if self.open.is_none() {
            if let Err(e) = self.open(event_loop) {
                self.error = Some(e);
                event_loop.exit();
            }
        }
    }

    fn window_event(&mut self, event_loop: &ActiveEventLoop, _: WindowId, event: WindowEvent) {
        match event {
            WindowEvent::CloseRequested => event_loop.exit(),
            WindowEvent::Resized(size) if size.width > 0 && size.height > 0 => {
                if let Some(o) = self.open.as_mut() {
                    o.config.width = size.width;
                    o.config.height = size.height;
                    o.surface.configure(&o.gpu.device, &o.config);
                }
            }
            _ => {}
        }
    }

    fn about_to_wait(&mut self, event_loop: &ActiveEventLoop) {
        self.frame();
        if let Some(start) = self.start {
            if start.elapsed().as_secs_f64() >= self.args.seconds {
                event_loop.exit();
            }
        }
    }
}

fn main() {
    let args = Args::parse();
    if !(args.seconds.is_finite() && args.seconds > 1.0 && args.seconds <= 3600.0) {
        eprintln!(
            "present_floor: --seconds {} must be within (1, 3600]: the first second is start-up",
            args.seconds
        );
        std::process::exit(2);
    }
    let event_loop = match EventLoop::new() {
        Ok(l) => l,
        Err(e) => {
            eprintln!(
                "present_floor: no display ({e}): run under one (xvfb-run -a for a virtual one)"
            );
            std::process::exit(1);
        }
    };
    event_loop.set_control_flow(ControlFlow::Poll);
    let mut app = App {
        args,
        open: None,
        start: None,
        last: None,
        periods: Vec::new(),
        error: None,
    };
    if let Err(e) = event_loop.run_app(&mut app) {
        eprintln!("present_floor: {e}");
        std::process::exit(1);
    }
    if let Some(e) = app.error {
        eprintln!("present_floor: {e}");
        std::process::exit(1);
    }
    let mut p = app.periods;
    if p.is_empty() {
        eprintln!("present_floor: no frame presented after the first second");
        std::process::exit(1);
    }
    p.sort();
    let ms = |d: Duration| d.as_secs_f64() * 1e3;
    let total: f64 = p.iter().map(|d| d.as_secs_f64()).sum();
    let at = |q: f64| ms(p[((p.len() - 1) as f64 * q).round() as usize]);
    println!(
        "frames {} fps {:.1} period p50 {:.2} ms p99 {:.2} ms max {:.2} ms",
        p.len(),
        p.len() as f64 / total,
        at(0.5),
        at(0.99),
        ms(p[p.len() - 1])
    );
}
