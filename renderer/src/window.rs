//! Windowed output: the renderer's [`Session`] driven from a winit event loop.
//!
//! Between window events the loop runs one session step (wait for the engine's frame or the deadline,
//! draw offscreen) and records the present pass into the same command buffer, so a frame reaches the
//! window in the same submit it is drawn in. Closing the window stops the renderer normally.
//!
//! `--fullscreen` fills one display (`--display NAME|INDEX`, the primary by default) with a borderless
//! fullscreen window, and sizes the offscreen image to it: in stereo each eye is half the display's
//! width and its full height, so each eye's aspect is its own half's. (With an HMD optics file the
//! eyes keep the optics' resolution and the present pass letterboxes them, never stretching.)
//! Displays are winit's monitors: X11 RandR outputs here (winit is built with its `x11` feature
//! only). Wayland would need winit's `wayland` feature (and libwayland-client at run time); on
//! Wayland a client cannot place itself, so borderless fullscreen on a named output is a request the
//! compositor may honour or not, and an output's name is the compositor's (e.g. `DP-1` on wlroots).
//!
//! The surface is configured for latency: mailbox where it is offered, else immediate, else FIFO
//! (`--present-mode` picks one; `--vsync` is FIFO), with `desired_maximum_frame_latency` 1
//! (`--frame-latency`). When `present` returns, the time goes into the frame's report
//! (`present_ns`, the latency harness's submit-to-present).

use std::sync::Arc;

use ipc_types::Intervention;

use winit::application::ApplicationHandler;
use winit::dpi::PhysicalSize;
use winit::event::WindowEvent;
use winit::event_loop::{ActiveEventLoop, ControlFlow, EventLoop};
use winit::window::{Fullscreen, Window, WindowId};

pub use crate::display::{DisplayArgs, DisplaySel, PresentChoice};
use crate::gpu::Gpu;
use crate::options::{RendererArgs, RendererError};
use crate::present::{self, PresentPass};
use crate::session::{FrameOutput, Session};

struct Windowed {
    session: Session,
    window: Arc<Window>,
    surface: wgpu::Surface<'static>,
    config: wgpu::SurfaceConfiguration,
    present: PresentPass,
    /// Whether the title says the engine is restarting.
    engine_down_shown: bool,
    queue: wgpu::Queue,
}

/// The window's surface as a [`FrameOutput`]: acquire an image and record the present pass into
/// the frame, present it after the submit.
struct SurfaceOutput<'a> {
    surface: &'a wgpu::Surface<'static>,
    config: &'a wgpu::SurfaceConfiguration,
    present: &'a PresentPass,
    window: &'a Window,
    queue: &'a wgpu::Queue,
    acquired: Option<wgpu::SurfaceTexture>,
    reconfigure: bool,
}

impl FrameOutput for SurfaceOutput<'_> {
    fn encode(&mut self, encoder: &mut wgpu::CommandEncoder) {
        match self.surface.get_current_texture() {
            wgpu::CurrentSurfaceTexture::Success(t)
            | wgpu::CurrentSurfaceTexture::Suboptimal(t) => {
                let size = (self.config.width, self.config.height);
                let view = t.texture.create_view(&wgpu::TextureViewDescriptor {
                    format: Some(self.present.view_format(size)),
                    ..Default::default()
                });
                self.present.encode(encoder, &view, size);
                self.acquired = Some(t);
            }
            wgpu::CurrentSurfaceTexture::Outdated | wgpu::CurrentSurfaceTexture::Lost => {
                self.reconfigure = true
            }
            // Timeout, occluded or validation: skip presenting this frame; the next one tries again.
            _ => {}
        }
    }

    fn present(&mut self) -> Option<u64> {
        let t = self.acquired.take()?;
        self.window.pre_present_notify();
        self.queue.present(t);
        Some(transport::now_ns())
    }

    fn mode(&self) -> (u32, u32) {
        (
            present_code(self.config.present_mode),
            self.config.desired_maximum_frame_latency,
        )
    }
}

/// The monitors as one line each, `INDEX: NAME WxH ...`, for errors and `lungdyn doctor`.
pub fn list_monitors(monitors: &[MonitorInfo]) -> String {
    monitors
        .iter()
        .enumerate()
        .map(|(i, m)| format!("{i}: {m}"))
        .collect::<Vec<_>>()
        .join("; ")
}

/// The index of the monitor `sel` names in `monitors`; without `sel`, the primary one (else the
/// first). Errors name what was asked and list the monitors there are.
#[allow(clippy::result_large_err)]
pub fn choose_monitor(
    monitors: &[MonitorInfo],
    sel: Option<&DisplaySel>,
) -> Result<usize, RendererError> {
    if monitors.is_empty() {
        return Err(RendererError::NoMonitors);
    }
    let listed = || list_monitors(monitors);
    match sel {
        None => Ok(monitors.iter().position(|m| m.primary).unwrap_or(0)),
        Some(DisplaySel::Index(i)) if *i < monitors.len() => Ok(*i),
        Some(DisplaySel::Index(i)) => Err(RendererError::DisplayIndex {
            index: *i,
            count: monitors.len(),
            monitors: listed(),
        }),
        Some(DisplaySel::Name(n)) => monitors.iter().position(|m| &m.name == n).ok_or_else(|| {
            RendererError::UnknownDisplay {
                name: n.clone(),
                monitors: listed(),
            }
        }),
    }
}

/// The present mode for `choice` among the surface's `supported` modes; `--vsync` is FIFO (every
/// surface has it). A named mode the surface lacks is refused, listing what it has.
#[allow(clippy::result_large_err)]
pub fn choose_present_mode(
    choice: PresentChoice,
    vsync: bool,
    supported: &[wgpu::PresentMode],
) -> Result<wgpu::PresentMode, RendererError> {
    use wgpu::PresentMode as M;
    let want = match (vsync, choice) {
        (true, _) | (false, PresentChoice::Fifo) => M::Fifo,
        (false, PresentChoice::Latency) => {
            return Ok([M::Mailbox, M::Immediate]
                .into_iter()
                .find(|m| supported.contains(m))
                .unwrap_or(M::Fifo))
        }
        (false, PresentChoice::Mailbox) => M::Mailbox,
        (false, PresentChoice::Immediate) => M::Immediate,
    };
    if supported.contains(&want) || want == M::Fifo {
        Ok(want)
    } else {
        Err(RendererError::PresentMode {
            wanted: format!("{want:?}").to_lowercase(),
            supported: supported
                .iter()
                .map(|m| format!("{m:?}").to_lowercase())
                .collect::<Vec<_>>()
                .join(", "),
        })
    }
}

/// The report's [`ipc_types::present_mode`] code of a wgpu present mode.
pub fn present_code(mode: wgpu::PresentMode) -> u32 {
    use ipc_types::present_mode as p;
    match mode {
        wgpu::PresentMode::Fifo | wgpu::PresentMode::AutoVsync => p::FIFO,
        wgpu::PresentMode::FifoRelaxed => p::FIFO_RELAXED,
        wgpu::PresentMode::Mailbox => p::MAILBOX,
        wgpu::PresentMode::Immediate | wgpu::PresentMode::AutoNoVsync => p::IMMEDIATE,
    }
}

struct App {
    args: RendererArgs,
    state: Option<Windowed>,
    error: Option<RendererError>,
}

impl App {
    fn open(&mut self, event_loop: &ActiveEventLoop) -> Result<(), RendererError> {
        let mut attributes = Window::default_attributes().with_title("lungdyn");
        if self.args.output.fullscreen {
            let handles: Vec<_> = event_loop.available_monitors().collect();
            let primary = event_loop.primary_monitor();
            let infos: Vec<MonitorInfo> = handles
                .iter()
                .map(|m| MonitorInfo::of(m, primary.as_ref()))
                .collect();
            let chosen = choose_monitor(&infos, self.args.output.display.as_ref())?;
            let m = &infos[chosen];
            // The offscreen image is the display's size: each eye half of it in stereo.
            self.args.screen_size = Some((m.width, m.height));
            eprintln!(
                "renderer: fullscreen on display {chosen}: {m} (of {})",
                infos.len()
            );
            attributes = attributes
                .with_fullscreen(Some(Fullscreen::Borderless(Some(handles[chosen].clone()))))
                .with_inner_size(PhysicalSize::new(m.width, m.height));
        } else {
            let (scene, rig) = self.args.scene_and_rig()?;
            let eyes = if scene.render.stereo { 2 } else { 1 };
            let (eye_width, eye_height) = rig.rig().eye_size(&scene.render);
            attributes =
                attributes.with_inner_size(PhysicalSize::new(eye_width * eyes, eye_height));
        }
        let window = Arc::new(
            event_loop
                .create_window(attributes)
                .map_err(|source| RendererError::Window { source })?,
        );
        let size = window.inner_size();
        let (gpu, surface) = Gpu::with_window(window.clone())?;
        let mut config = surface
            .get_default_config(&gpu.adapter, size.width.max(1), size.height.max(1))
            .ok_or_else(|| RendererError::CannotPresent {
                adapter: gpu.info.name.clone(),
            })?;
        let caps = surface.get_capabilities(&gpu.adapter);
        // An sRGB surface where there is one (the default is the surface's first format, which
        // some drivers list as UNORM): the frame is sRGB, and so is the filtered (scaled) copy.
        config.format = present::surface_format(&caps.formats, config.format);
        // The plain-bytes view of the surface for the exact copy, where the adapter allows it.
        let surface_views = gpu
            .adapter
            .get_downlevel_capabilities()
            .flags
            .contains(wgpu::DownlevelFlags::SURFACE_VIEW_FORMATS);
        config.present_mode = choose_present_mode(
            self.args.output.present_mode,
            self.args.output.vsync,
            &caps.present_modes,
        )?;
        config.desired_maximum_frame_latency = self.args.output.frame_latency;
        let session = Session::new(&self.args, gpu)?;
        let present = PresentPass::new(
            &session.gpu.device,
            session.renderer.color_view(),
            session
                .renderer
                .color_bytes_view()
                .filter(|_| surface_views),
            session.renderer.image_size(),
            config.format,
        );
        // The surface is viewed as plain bytes for the exact copy (a window of the frame's size).
        config.view_formats = present.surface_view_formats();
        surface.configure(&session.gpu.device, &config);
        eprintln!(
            "renderer: presenting {:?} with frame latency {} (the surface offers {:?}); the frame \
             {:?} is copied {} into the window's {}x{}",
            config.present_mode,
            config.desired_maximum_frame_latency,
            caps.present_modes,
            session.renderer.image_size(),
            if present.is_exact((config.width, config.height)) {
                "texel for texel"
            } else {
                "scaled"
            },
            config.width,
            config.height,
        );
        let queue = session.gpu.queue.clone();
        self.state = Some(Windowed {
            session,
            window,
            surface,
            config,
            present,
            engine_down_shown: false,
            queue,
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
            engine_down_shown,
            queue,
        } = w;
        let mut output = SurfaceOutput {
            surface,
            config,
            present,
            window,
            queue,
            acquired: None,
            reconfigure: false,
        };
        let result = session.step(&mut output);
        let down = session.engine_down();
        if down != *engine_down_shown {
            *engine_down_shown = down;
            window.set_title(if down {
                "lungdyn — ENGINE RESTARTING: last frame shown, stale"
            } else {
                "lungdyn"
            });
        }
        if output.reconfigure {
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

impl std::fmt::Display for MonitorInfo {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let name = if self.name.is_empty() {
            "(unnamed)"
        } else {
            &self.name
        };
        write!(f, "{name} {}x{}", self.width, self.height)?;
        if let Some(r) = self.refresh_mhz {
            write!(f, " @ {:.2} Hz", r as f64 / 1000.0)?;
        }
        if self.primary {
            f.write_str(" (primary)")?;
        }
        write!(f, ", {} modes", self.modes)
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

#[cfg(test)]
mod tests {
    use super::*;
    use clap::Parser;

    fn monitor(name: &str, width: u32, primary: bool) -> MonitorInfo {
        MonitorInfo {
            name: name.into(),
            width,
            height: 1080,
            refresh_mhz: Some(90_000),
            modes: 3,
            primary,
        }
    }

    #[test]
    fn a_display_is_chosen_by_name_or_index_and_the_primary_by_default() {
        let list = [monitor("DP-1", 1920, false), monitor("HDMI-1", 2880, true)];
        assert_eq!(choose_monitor(&list, None).unwrap(), 1);
        assert_eq!(choose_monitor(&[monitor("a", 1, false)], None).unwrap(), 0);
        let by = |s: &str| choose_monitor(&list, Some(&s.parse().unwrap())).ok();
        assert_eq!(by("0"), Some(0));
        assert_eq!(by("HDMI-1"), Some(1));
        assert_eq!(by(" DP-1 "), Some(0));
    }

    #[test]
    fn an_unknown_or_out_of_range_display_is_refused_listing_the_displays() {
        let list = [monitor("DP-1", 1920, false), monitor("HDMI-1", 2880, true)];
        let e = choose_monitor(&list, Some(&"dp-1".parse().unwrap()))
            .unwrap_err()
            .to_string();
        assert!(e.contains("--display dp-1: no display of that name"), "{e}");
        assert!(
            e.contains(
                "0: DP-1 1920x1080 @ 90.00 Hz, 3 modes; 1: HDMI-1 2880x1080 @ 90.00 Hz (primary)"
            ),
            "{e}"
        );
        let e = choose_monitor(&list, Some(&DisplaySel::Index(2)))
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("--display 2: there are only 2 display(s), 0 to 1"),
            "{e}"
        );
        assert!(e.contains("HDMI-1"), "{e}");
        let e = choose_monitor(&[], None).unwrap_err().to_string();
        assert!(e.contains("no monitors"), "{e}");
        assert!("".parse::<DisplaySel>().unwrap_err().contains("empty"));
        assert!("99999999999999999999999".parse::<DisplaySel>().is_err());
    }

    #[test]
    fn the_present_mode_is_the_least_latency_offered_unless_one_is_named() {
        use wgpu::PresentMode as M;
        let all = [M::Fifo, M::FifoRelaxed, M::Immediate, M::Mailbox];
        let l = PresentChoice::Latency;
        assert_eq!(choose_present_mode(l, false, &all).unwrap(), M::Mailbox);
        assert_eq!(
            choose_present_mode(l, false, &[M::Fifo, M::Immediate]).unwrap(),
            M::Immediate
        );
        assert_eq!(choose_present_mode(l, false, &[M::Fifo]).unwrap(), M::Fifo);
        assert_eq!(choose_present_mode(l, false, &[]).unwrap(), M::Fifo);
        assert_eq!(choose_present_mode(l, true, &all).unwrap(), M::Fifo);
        let mb = PresentChoice::Mailbox;
        assert_eq!(choose_present_mode(mb, false, &all).unwrap(), M::Mailbox);
        let e = choose_present_mode(mb, false, &[M::Fifo, M::Immediate])
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("--present-mode mailbox: this surface offers only fifo, immediate"),
            "{e}"
        );
        assert_eq!(present_code(M::Mailbox), ipc_types::present_mode::MAILBOX);
        assert_eq!(present_code(M::Fifo), ipc_types::present_mode::FIFO);
        assert_eq!(
            present_code(M::Immediate),
            ipc_types::present_mode::IMMEDIATE
        );
    }

    #[derive(Parser)]
    struct Cli {
        #[command(flatten)]
        d: DisplayArgs,
    }

    #[test]
    fn display_options_pass_through_to_the_renderer_unchanged() {
        for args in [
            vec![
                "--fullscreen",
                "--display=HDMI-1",
                "--present-mode=immediate",
                "--frame-latency=2",
            ],
            vec!["--window", "--vsync", "--frame-latency=1"],
            vec!["--xr"],
            vec![],
        ] {
            let d = Cli::try_parse_from(std::iter::once("x").chain(args.iter().copied()))
                .unwrap()
                .d;
            let again = Cli::try_parse_from(std::iter::once("x".to_string()).chain(d.to_args()))
                .unwrap()
                .d;
            assert_eq!(format!("{d:?}"), format!("{again:?}"), "{args:?}");
        }
        assert!(Cli::try_parse_from(["x", "--display", "0"]).is_err());
        assert!(Cli::try_parse_from(["x", "--vsync"]).is_err());
        assert!(Cli::try_parse_from(["x", "--xr", "--fullscreen"]).is_err());
        assert!(Cli::try_parse_from(["x", "--xr", "--present-mode", "fifo"]).is_err());
        assert!(Cli::try_parse_from(["x", "--window", "--frame-latency", "4"]).is_err());
    }
}
