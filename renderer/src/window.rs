//! Windowed output: the renderer's [`Session`] driven from a winit event loop.
//!
//! Between window events the loop runs one session step (wait for the engine's frame or the deadline,
//! draw offscreen) and records the present pass into the same command buffer, so a frame reaches the
//! window in the same submit it is drawn in. Closing the window stops the renderer normally.

use std::sync::Arc;

use ipc_types::Intervention;

use winit::application::ApplicationHandler;
use winit::dpi::PhysicalSize;
use winit::event::WindowEvent;
use winit::event_loop::{ActiveEventLoop, ControlFlow, EventLoop};
use winit::window::{Window, WindowId};

use crate::gpu::Gpu;
use crate::present::PresentPass;
use crate::process::{RendererArgs, RendererError, Session};

struct Windowed {
    session: Session,
    window: Arc<Window>,
    surface: wgpu::Surface<'static>,
    config: wgpu::SurfaceConfiguration,
    present: PresentPass,
}

struct App {
    args: RendererArgs,
    state: Option<Windowed>,
    error: Option<RendererError>,
}

impl App {
    fn open(&mut self, event_loop: &ActiveEventLoop) -> Result<(), RendererError> {
        let (scene, rig) = self.args.scene_and_rig()?;
        let eyes = if scene.render.stereo { 2 } else { 1 };
        let (eye_width, eye_height) = rig.rig().eye_size(&scene.render);
        let size = PhysicalSize::new(eye_width * eyes, eye_height);
        let window = Arc::new(
            event_loop
                .create_window(
                    Window::default_attributes()
                        .with_title("lungdyn")
                        .with_inner_size(size),
                )
                .map_err(|source| RendererError::Window { source })?,
        );
        let (gpu, surface) = Gpu::with_window(window.clone())?;
        let mut config = surface
            .get_default_config(&gpu.adapter, size.width, size.height)
            .ok_or_else(|| RendererError::CannotPresent {
                adapter: gpu.info.name.clone(),
            })?;
        config.present_mode = if self.args.vsync {
            wgpu::PresentMode::AutoVsync
        } else {
            wgpu::PresentMode::AutoNoVsync
        };
        surface.configure(&gpu.device, &config);
        let session = Session::new(&self.args, gpu)?;
        let present = PresentPass::new(
            &session.gpu.device,
            session.renderer.color_view(),
            config.format,
        );
        self.state = Some(Windowed {
            session,
            window,
            surface,
            config,
            present,
        });
        Ok(())
    }

    fn fail(&mut self, event_loop: &ActiveEventLoop, e: RendererError) {
        self.error = Some(e);
        event_loop.exit();
    }
}

impl ApplicationHandler for App {
    fn resumed(&mut self, event_loop: &ActiveEventLoop) {
        if self.state.is_none() {
            if let Err(e) = self.open(event_loop) {
                self.fail(event_loop, e);
            }
        }
    }

    fn window_event(&mut self, event_loop: &ActiveEventLoop, _id: WindowId, event: WindowEvent) {
        let Some(w) = self.state.as_mut() else { return };
        match event {
            WindowEvent::CloseRequested => event_loop.exit(),
            WindowEvent::Resized(size) if size.width > 0 && size.height > 0 => {
                w.config.width = size.width;
                w.config.height = size.height;
                w.surface.configure(&w.session.gpu.device, &w.config);
            }
            // A trainee's interventions on a tension pneumothorax: N needle decompression, C chest
            // tube, O occlusive dressing (sent to the engine, whose answer, read from the
            // control-reply stream, shows on the HUD in words with its time); H the HUD.
            WindowEvent::KeyboardInput { event, .. }
                if event.state == winit::event::ElementState::Pressed && !event.repeat =>
            {
                let text = event.logical_key.to_text();
                if matches!(text, Some("h" | "H")) {
                    let on = w.session.toggle_hud();
                    eprintln!("renderer: key: HUD {}", if on { "on" } else { "off" });
                    return;
                }
                let action = text.and_then(key_action);
                if let Some(kind) = action {
                    match w.session.send_action(kind) {
                        Ok(Some(side)) => {
                            eprintln!("renderer: key: {kind} on the {} lung sent", side.name())
                        }
                        Ok(None) => eprintln!(
                            "renderer: key: {kind} needs a tension pneumothorax scene; ignored"
                        ),
                        Err(e) => {
                            self.fail(event_loop, e);
                        }
                    }
                }
            }
            _ => {}
        }
    }

    fn about_to_wait(&mut self, event_loop: &ActiveEventLoop) {
        let Some(w) = self.state.as_mut() else { return };
        if w.session.should_stop() {
            event_loop.exit();
            return;
        }
        let Windowed {
            session,
            surface,
            present,
            config,
            window,
        } = w;
        let mut acquired = None;
        let mut reconfigure = false;
        let result = session.step(|encoder| match surface.get_current_texture() {
            wgpu::CurrentSurfaceTexture::Success(t)
            | wgpu::CurrentSurfaceTexture::Suboptimal(t) => {
                let view = t.texture.create_view(&Default::default());
                present.encode(encoder, &view);
                acquired = Some(t);
            }
            wgpu::CurrentSurfaceTexture::Outdated | wgpu::CurrentSurfaceTexture::Lost => {
                reconfigure = true
            }
            // Timeout, occluded or validation: skip presenting this frame; the next one tries again.
            _ => {}
        });
        if let Some(t) = acquired {
            window.pre_present_notify();
            session.gpu.queue.present(t);
        }
        if reconfigure {
            surface.configure(&session.gpu.device, config);
        }
        if let Err(e) = result {
            self.fail(event_loop, e);
        }
    }
}

/// What a key sends to the engine: N a needle decompression, C a chest tube, O an occlusive
/// dressing, for the scene's tension pneumothorax; `None` for any other key.
pub fn key_action(text: &str) -> Option<Intervention> {
    match text {
        "n" | "N" => Some(Intervention::NeedleDecompression),
        "c" | "C" => Some(Intervention::ChestTube),
        "o" | "O" => Some(Intervention::OcclusiveDressing),
        _ => None,
    }
}

/// Run the renderer in a window until it is closed, the process is signalled, or `--seconds` end.
pub fn run(args: &RendererArgs) -> Result<(), RendererError> {
    args.process.run_ns()?;
    let event_loop = EventLoop::new().map_err(|source| RendererError::NoDisplay { source })?;
    event_loop.set_control_flow(ControlFlow::Poll);
    let mut app = App {
        args: args.clone(),
        state: None,
        error: None,
    };
    event_loop
        .run_app(&mut app)
        .map_err(|source| RendererError::EventLoop { source })?;
    transport::notify::stopping();
    if let Some(state) = &app.state {
        state.session.finish();
    }
    match app.error {
        Some(e) => Err(e),
        None => Ok(()),
    }
}

/// One display as winit sees it (what `lungdyn doctor` lists and `--display` picks from).
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct MonitorInfo {
    /// The output's name (X11: RandR output, e.g. `DP-1`); empty when the server gives none.
    pub name: String,
    /// Current size, pixels.
    pub width: u32,
    /// Current size, pixels.
    pub height: u32,
    /// Current refresh rate, mHz, when known.
    pub refresh_mhz: Option<u32>,
    /// Video modes it offers (for exclusive fullscreen).
    pub modes: usize,
    /// Whether it is the primary output.
    pub primary: bool,
}

impl MonitorInfo {
    fn of(
        m: &winit::monitor::MonitorHandle,
        primary: Option<&winit::monitor::MonitorHandle>,
    ) -> Self {
        let size = m.size();
        Self {
            name: m.name().unwrap_or_default(),
            width: size.width,
            height: size.height,
            refresh_mhz: m.refresh_rate_millihertz(),
            modes: m.video_modes().count(),
            primary: primary == Some(m),
        }
    }
}

struct ListMonitors(Option<Vec<MonitorInfo>>);

impl ApplicationHandler for ListMonitors {
    fn resumed(&mut self, event_loop: &ActiveEventLoop) {
        let primary = event_loop.primary_monitor();
        self.0 = Some(
            event_loop
                .available_monitors()
                .map(|m| MonitorInfo::of(&m, primary.as_ref()))
                .collect(),
        );
        event_loop.exit();
    }

    fn window_event(&mut self, _: &ActiveEventLoop, _: WindowId, _: WindowEvent) {}
}

/// The displays of the session (X11), in winit's order — the order `--display INDEX` counts in.
/// Opens and closes an event loop, so call it once per process and never beside [`run`].
pub fn monitors() -> Result<Vec<MonitorInfo>, winit::error::EventLoopError> {
    let mut list = ListMonitors(None);
    EventLoop::new()?.run_app(&mut list)?;
    Ok(list.0.unwrap_or_default())
}
