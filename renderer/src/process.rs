//! The renderer process: its options ([`crate::options`]), one [`Session`] ([`crate::session`])
//! driven headless here, in a window ([`crate::window`]) or by an OpenXR runtime
//! ([`crate::xr_runtime`]). Each of those depends on the session one way; this module only chooses.

pub use crate::options::{HudSwitch, RendererArgs, RendererError, SnapshotView};
use crate::session::check_predict_ms;
pub use crate::session::{
    quiet_mesa, FrameOutput, Headless, Ports, Session, SessionStats, Snapshots,
};

use transport::process::pin_to_core;

use crate::gpu::Gpu;

/// Run the renderer until terminated (or `--seconds` elapse): headless, or in a window.
pub fn run(args: &RendererArgs) -> Result<(), RendererError> {
    // Pinned before any other thread exists: a thread inherits its creator's affinity, so the stop
    // handler, the window system's threads and the driver's (lavapipe's rasterisers, a GPU driver's
    // submission threads) all stay on the renderer's core, off the engine's. Pinned later (as before),
    // only the main thread was: lavapipe's `llvmpipe-N` threads ran on every core.
    pin_to_core(args.process.cpu, "renderer")?;
    transport::stop::install()?;
    quiet_mesa();
    check_predict_ms(args.predict_ms)?;
    // The scene and its calibration and optics files are checked before a window or the GPU opens.
    args.scene_and_rig()?;
    if args.output.shown() {
        return crate::window::run(args);
    }
    if args.output.xr {
        return run_xr(args);
    }
    // Validate the options before opening the GPU (slow on software adapters).
    args.process.run_ns()?;
    let mut session = Session::new(args, Gpu::new()?)?;
    while !session.should_stop() {
        session.step(&mut Headless)?;
    }
    transport::notify::stopping();
    session.finish();
    Ok(())
}

/// Run the renderer into an OpenXR runtime until terminated, `--seconds` end or the runtime ends
/// the session.
#[cfg(feature = "openxr")]
#[allow(clippy::result_large_err)] // RendererError is large everywhere (see scene_and_rig)
fn run_xr(args: &RendererArgs) -> Result<(), RendererError> {
    use crate::xr_runtime::{XrOutput, XrSystem};
    let xr = |e: crate::xr_runtime::XrError| RendererError::Xr(e.to_string());
    args.process.run_ns()?;
    let system = XrSystem::open().map_err(xr)?;
    let mut args = args.clone();
    args.xr_eye_size = Some(system.eye_size);
    args.xr_blend = Some(system.blend());
    let look = args.scene_and_rig()?.0.render.look;
    transport::process::say(&format!(
        "renderer[{}]: openxr: {:?} environment blend, {}x{} per eye, {} look",
        args.process.instance,
        system.blend(),
        system.eye_size.0,
        system.eye_size.1,
        look.name()
    ));
    let (gpu, binding) = system.gpu().map_err(xr)?;
    let mut output = XrOutput::new(system, &gpu, &binding).map_err(xr)?;
    let mut session = Session::new(&args, gpu)?;
    output.attach(
        &session.gpu.device,
        session.renderer.color_view(),
        session.renderer.image_size(),
    );
    let mut result = Ok(());
    while !session.should_stop() && !output.should_stop() {
        if let Err(e) = session.step(&mut output) {
            result = Err(e);
            break;
        }
    }
    // Ended as OpenXR asks when the renderer stops (signal, --seconds); a runtime that ended it
    // itself needs nothing more.
    if let Err(e) = output.shutdown() {
        output.error.get_or_insert(e);
    }
    transport::process::say(&format!(
        "renderer[{}]: openxr: {}",
        args.process.instance, output.stats
    ));
    let failed = output.error.take();
    // The session and its swapchain go before the device they were made on, and wgpu's views of
    // the swapchain's images before the swapchain.
    output.release_images(&session.gpu.device);
    drop(output);
    transport::notify::stopping();
    session.finish();
    result?;
    failed.map_or(Ok(()), |e| Err(xr(e)))
}

/// Without the `openxr` feature (a `--no-default-features` build) `--xr` says how to get it.
#[cfg(not(feature = "openxr"))]
#[allow(clippy::result_large_err)] // RendererError is large everywhere (see scene_and_rig)
fn run_xr(_: &RendererArgs) -> Result<(), RendererError> {
    Err(RendererError::Xr(
        "this build has no OpenXR support (built with --no-default-features): build it with the \
         default features or `--features openxr` (the OpenXR loader is opened at run time, so building \
         needs no system library), then install an OpenXR runtime (Monado) or set XR_RUNTIME_JSON"
            .into(),
    ))
}
