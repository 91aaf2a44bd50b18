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
        "no GPU adapter found ({detail}); on a machine without a GPU install Mesa's lavapipe, a \
         software Vulkan driver: `sudo apt-get install mesa-vulkan-drivers libvulkan1` (`./run demo` \
         and `./run test` install it)"
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

/// Find the adapter the renderer would open, without opening a device: its one-line description,
/// or the error naming what to install. A launcher calls it before any long work.
pub fn probe_adapter() -> Result<String, GpuError> {
    let instance =
        wgpu::Instance::new(wgpu::InstanceDescriptor::new_without_display_handle_from_env());
    let adapter = pollster::block_on(instance.request_adapter(&wgpu::RequestAdapterOptions {
        power_preference: wgpu::PowerPreference::HighPerformance,
        ..Default::default()
    }))
    .map_err(|e| GpuError::NoAdapter {
        detail: e.to_string(),
    })?;
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
        let adapter = pollster::block_on(instance.request_adapter(&wgpu::RequestAdapterOptions {
            power_preference: wgpu::PowerPreference::HighPerformance,
            compatible_surface: surface,
            ..Default::default()
        }))
        .map_err(|e| GpuError::NoAdapter {
            detail: e.to_string(),
        })?;
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
