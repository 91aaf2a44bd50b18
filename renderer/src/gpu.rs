//! GPU context: one wgpu instance, adapter, device and queue (Vulkan: lavapipe in CI, the real
//! driver on the HMD workstation).

use thiserror::Error;

/// An open GPU.
pub struct Gpu {
    /// The wgpu instance (kept for creating window surfaces).
    pub instance: wgpu::Instance,
    /// The adapter the device was opened on.
    pub adapter: wgpu::Adapter,
    /// The device.
    pub device: wgpu::Device,
    /// Its queue.
    pub queue: wgpu::Queue,
    /// Adapter name, driver, backend.
    pub info: wgpu::AdapterInfo,
    /// Whether GPU timestamp queries are available (per-frame GPU time).
    pub timestamps: bool,
}

/// Errors opening the GPU.
#[derive(Debug, Error)]
pub enum GpuError {
    /// No Vulkan adapter.
    #[error(
        "no GPU adapter found ({detail}; asked {ADAPTER_TRIES} times over {:.1} s); on a machine \
         without a GPU install Mesa's lavapipe, a software Vulkan driver: `sudo apt-get install \
         mesa-vulkan-drivers libvulkan1` (`./run demo` and `./run test` install it); where the \
         machine has a GPU, its driver did not offer it (`lungdyn doctor` checks)",
        ADAPTER_PAUSES_MS.iter().sum::<u64>() as f64 / 1000.0
    )]
    NoAdapter {
        /// wgpu's reason.
        detail: String,
    },
    /// The adapter refused the device.
    #[error("the GPU adapter {adapter} refused to open a device: {detail}")]
    Device {
        /// Adapter name.
        adapter: String,
        /// wgpu's reason.
        detail: String,
    },
}

/// Pauses between the tries for an adapter. A GPU can be briefly unavailable: on an NVIDIA H200
/// the next process found no adapter right after a storm of SIGKILLed renderers (`lungdyn faults`,
/// docs/gpu), while the driver was still tearing their contexts down; a few tries over 1.5 s ride
/// that out, and a machine with no GPU at all waits no longer than that for its error.
const ADAPTER_PAUSES_MS: [u64; 4] = [100, 200, 400, 800];
/// Tries for an adapter: the first and one after each pause.
const ADAPTER_TRIES: usize = ADAPTER_PAUSES_MS.len() + 1;

/// The best adapter (`WGPU_BACKEND`, `WGPU_ADAPTER_NAME` honoured), asked [`ADAPTER_TRIES`] times
/// before giving up; a line on stderr says when the first try found none.
fn request_adapter(
    instance: &wgpu::Instance,
    surface: Option<&wgpu::Surface<'_>>,
) -> Result<wgpu::Adapter, GpuError> {
    let ask = || {
        pollster::block_on(instance.request_adapter(&wgpu::RequestAdapterOptions {
            power_preference: wgpu::PowerPreference::HighPerformance,
            compatible_surface: surface,
            ..Default::default()
        }))
    };
    let mut last = match ask() {
        Ok(a) => return Ok(a),
        Err(e) => e,
    };
    eprintln!(
        "lungdyn: no GPU adapter yet ({last}); asking again for up to {:.1} s",
        ADAPTER_PAUSES_MS.iter().sum::<u64>() as f64 / 1000.0
    );
    for pause in ADAPTER_PAUSES_MS {
        std::thread::sleep(std::time::Duration::from_millis(pause));
        match ask() {
            Ok(a) => return Ok(a),
            Err(e) => last = e,
        }
    }
    Err(GpuError::NoAdapter {
        detail: last.to_string(),
    })
}

/// Find the adapter the renderer would open, without opening a device: its one-line description,
/// or the error naming what to install. A launcher calls it before any long work.
pub fn probe_adapter() -> Result<String, GpuError> {
    let instance =
        wgpu::Instance::new(wgpu::InstanceDescriptor::new_without_display_handle_from_env());
    let adapter = request_adapter(&instance, None)?;
    let info = adapter.get_info();
    let software = if info.device_type == wgpu::DeviceType::Cpu {
        ", a software rasteriser"
    } else {
        ""
    };
    Ok(format!(
        "{} ({:?}, {} {}{software})",
        info.name, info.backend, info.driver, info.driver_info
    ))
}

impl Gpu {
    /// Open the best adapter (honours `WGPU_BACKEND`, `WGPU_ADAPTER_NAME`).
    pub fn new() -> Result<Self, GpuError> {
        let instance =
            wgpu::Instance::new(wgpu::InstanceDescriptor::new_without_display_handle_from_env());
        Self::open(instance, None)
    }

    /// Open a GPU that can present to `window`, and the window's surface.
    pub fn with_window(
        window: std::sync::Arc<winit::window::Window>,
    ) -> Result<(Self, wgpu::Surface<'static>), GpuError> {
        let instance =
            wgpu::Instance::new(wgpu::InstanceDescriptor::new_without_display_handle_from_env());
        let surface = instance
            .create_surface(window)
            .map_err(|e| GpuError::NoAdapter {
                detail: format!("cannot create a surface for the window: {e}"),
            })?;
        let gpu = Self::open(instance, Some(&surface))?;
        Ok((gpu, surface))
    }

    fn open(
        instance: wgpu::Instance,
        surface: Option<&wgpu::Surface<'_>>,
    ) -> Result<Self, GpuError> {
        let adapter = request_adapter(&instance, surface)?;
        let info = adapter.get_info();
        let timestamps = adapter.features().contains(wgpu::Features::TIMESTAMP_QUERY);
        let required_features = if timestamps {
            wgpu::Features::TIMESTAMP_QUERY
        } else {
            wgpu::Features::empty()
        };
        let (device, queue) = pollster::block_on(adapter.request_device(&wgpu::DeviceDescriptor {
            label: Some("lungdyn"),
            required_features,
            required_limits: adapter.limits(),
            ..Default::default()
        }))
        .map_err(|e| GpuError::Device {
            adapter: info.name.clone(),
            detail: e.to_string(),
        })?;
        Ok(Self {
            instance,
            adapter,
            device,
            queue,
            info,
            timestamps,
        })
    }

    /// One line naming the adapter, for reports.
    pub fn describe(&self) -> String {
        format!(
            "{} ({:?}, {} {})",
            self.info.name, self.info.backend, self.info.driver, self.info.driver_info
        )
    }

    /// For tests: the GPU — or, when there is none, a test failure naming the package to install,
    /// unless the person running the tests opted out (`LUNGDYN_SKIP_GPU=1`): then `None`, and the skip
    /// is said on the terminal and counted in the skip log (`lungdyn_needs`).
    pub fn for_tests() -> Option<Self> {
        lungdyn_needs::require(lungdyn_needs::Need::Gpu, Self::new())
    }
}
