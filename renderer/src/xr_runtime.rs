//! OpenXR output, the runtime-facing part (cargo feature `openxr`; `--xr`). Kept thin: every
//! decision it takes is in [`crate::xr`] and tested there. Run against Monado (null compositor,
//! simulated headset, lavapipe) by deploy/xr_check.sh and tests/tests/openxr.rs; what that does
//! not verify (a real headset, additive blend on optical see-through hardware, timing on a real
//! display) is listed in docs/DEPLOY.md, "OpenXR".
//!
//! * The loader is opened at run time (`openxr`'s `loaded` feature: `libopenxr_loader.so.1`), so
//!   building needs no system library; without it, or without a runtime, `--xr` fails naming
//!   what to install.
//! * Vulkan through `XR_KHR_vulkan_enable2`: the runtime creates the Vulkan instance and device
//!   (adding the extensions it needs to the ones wgpu asks for), and wgpu wraps them through its
//!   hal interop (`wgpu::hal::vulkan::Instance::from_raw`, `Adapter::device_from_raw`,
//!   `Instance::from_hal`, `Adapter::create_device_from_hal`). wgpu then owns and destroys them.
//! * One swapchain two eyes wide: the renderer's one deformation pass and its side-by-side draw
//!   fill the offscreen image, which the present pass draws 1:1 into the acquired swapchain image
//!   (a render pass: the image is left in COLOR_ATTACHMENT_OPTIMAL, as `XR_KHR_vulkan_enable2`
//!   expects at release); the projection layer's two views name the left and right halves.
//! * `xrWaitFrame`'s predicted display time, converted to CLOCK_MONOTONIC
//!   (`XR_KHR_convert_timespec_time`, [`crate::xr::XrClock`]), is the instant the HMD pose is
//!   predicted to; each eye's offset and field of view come from the runtime's views in the head's
//!   space (the external tracker still gives the head's pose on the patient).
//! * The environment blend mode is additive wherever the runtime offers it (optical see-through).

use ash::vk::{self, Handle};
use openxr as xr;
use wgpu::hal;

use crate::camera::{FAR_MM, NEAR_MM};
use crate::gpu::Gpu;
use crate::present::PresentPass;
use crate::xr::{BlendMode, Fov, XrClock, XrEye, XrStats};

const VIEW_TYPE: xr::ViewConfigurationType = xr::ViewConfigurationType::PRIMARY_STEREO;

/// Why the OpenXR output could not start or stopped.
#[derive(Debug, thiserror::Error)]
pub enum XrError {
    /// No OpenXR loader library.
    #[error(
        "no OpenXR loader ({0}): install the OpenXR loader (Debian/Ubuntu: `apt-get install \
         libopenxr-loader1`) and a runtime for the headset (Monado: its packages per \
         distribution are in docs/DEPLOY.md, \"OpenXR\"), or run without --xr"
    )]
    NoLoader(String),
    /// The loader found no active runtime.
    #[error(
        "no OpenXR runtime ({0}): install the headset's runtime and make it the active one, or set \
         XR_RUNTIME_JSON to its manifest. Monado: on Ubuntu 22.04 or newer and Debian 13 (trixie) or \
         newer, `apt-get install libopenxr1-monado` (manifest /usr/share/openxr/1/openxr_monado.json); \
         Debian 12 (bookworm) has no Monado package — build it from source \
         (https://monado.freedesktop.org; deploy/xr_check.sh builds a pinned, headless one) and set \
         XR_RUNTIME_JSON to its build/openxr_monado-dev.json"
    )]
    NoRuntime(String),
    /// The runtime lacks an extension the renderer needs.
    #[error(
        "the OpenXR runtime lacks {0}, which the renderer needs (Vulkan through \
         XR_KHR_vulkan_enable2; display times on CLOCK_MONOTONIC through XR_KHR_convert_timespec_time)"
    )]
    MissingExtension(&'static str),
    /// No head-mounted display.
    #[error(
        "no headset: the OpenXR runtime has no head-mounted display ({0}); connect and power it on"
    )]
    NoHeadset(String),
    /// The runtime needs another Vulkan version.
    #[error(
        "the OpenXR runtime needs Vulkan {min} to {max}.x; the renderer would make its instance \
         for {used} (the Vulkan loader's version, at most 1.3)"
    )]
    VulkanVersion {
        /// Lowest supported.
        min: String,
        /// Highest supported major version.
        max: u16,
        /// The version the instance would be made for.
        used: String,
    },
    /// No usable environment blend mode.
    #[error(
        "the OpenXR runtime offers no environment blend mode the renderer can use (offered: {0})"
    )]
    NoBlendMode(String),
    /// No swapchain format the renderer can fill.
    #[error(
        "the OpenXR runtime offers no swapchain format the renderer can fill (VkFormats {0:?})"
    )]
    NoFormat(Vec<i64>),
    /// An OpenXR call failed.
    #[error("OpenXR {what} failed: {result}")]
    Call {
        /// The call.
        what: &'static str,
        /// Its result.
        result: xr::sys::Result,
    },
    /// A Vulkan call failed.
    #[error("Vulkan {what} failed: {detail}")]
    Vulkan {
        /// The call.
        what: &'static str,
        /// Why.
        detail: String,
    },
}

fn call<T>(what: &'static str, r: xr::Result<T>) -> Result<T, XrError> {
    r.map_err(|result| XrError::Call { what, result })
}

fn vulkan(what: &'static str, detail: impl std::fmt::Display) -> XrError {
    XrError::Vulkan {
        what,
        detail: detail.to_string(),
    }
}

/// The Vulkan version the instance is made for: the one wgpu itself would ask for. wgpu takes the
/// device's own version as the version in use (a 1.2 entry point is called through the core table
/// when the GPU is 1.2 or newer), so an instance made for less would hand it null pointers; hence
/// the loader's version, capped at 1.3 ([`crate::xr::vulkan_instance_version`]).
fn instance_version_of(vk_entry: &ash::Entry) -> Result<u32, XrError> {
    // SAFETY: a query of the loader's version through an entry that was loaded successfully.
    let loader = unsafe { vk_entry.try_enumerate_instance_version() }
        .map_err(|e| vulkan("vkEnumerateInstanceVersion", e))?
        .unwrap_or(vk::API_VERSION_1_0);
    crate::xr::vulkan_instance_version(loader).ok_or_else(|| {
        vulkan(
            "choosing the Vulkan version",
            format!(
                "the Vulkan loader offers only {}.{}; the renderer needs 1.1 or newer (update \
                 libvulkan1)",
                vk::api_version_major(loader),
                vk::api_version_minor(loader)
            ),
        )
    })
}

/// [`instance_version_of`] with libvulkan loaded for the question.
fn instance_version() -> Result<u32, XrError> {
    // SAFETY: loading libvulkan runs its initialisers, as any Vulkan application does.
    let vk_entry = unsafe { ash::Entry::load() }.map_err(|e| vulkan("loading libvulkan", e))?;
    instance_version_of(&vk_entry)
}

/// The runtime's environment blend mode as [`BlendMode`] (others are ignored).
fn blend_of(m: xr::EnvironmentBlendMode) -> Option<BlendMode> {
    match m {
        xr::EnvironmentBlendMode::OPAQUE => Some(BlendMode::Opaque),
        xr::EnvironmentBlendMode::ADDITIVE => Some(BlendMode::Additive),
        xr::EnvironmentBlendMode::ALPHA_BLEND => Some(BlendMode::AlphaBlend),
        _ => None,
    }
}

fn xr_blend(m: BlendMode) -> xr::EnvironmentBlendMode {
    match m {
        BlendMode::Opaque => xr::EnvironmentBlendMode::OPAQUE,
        BlendMode::Additive => xr::EnvironmentBlendMode::ADDITIVE,
        BlendMode::AlphaBlend => xr::EnvironmentBlendMode::ALPHA_BLEND,
    }
}

/// The loader, the runtime's instance and the headset: everything before any GPU work, so a
/// machine without a runtime is told at once.
pub struct XrSystem {
    instance: xr::Instance,
    system: xr::SystemId,
    blend: BlendMode,
    /// Per-eye recommended image size.
    pub eye_size: (u32, u32),
}

impl XrSystem {
    /// Open the loader, the runtime and its head-mounted display.
    pub fn open() -> Result<Self, XrError> {
        // SAFETY: the loader found on the library path is assumed to conform to the OpenXR spec
        // (the only requirement of `Entry::load`).
        let entry =
            unsafe { xr::Entry::load(&()) }.map_err(|e| XrError::NoLoader(e.to_string()))?;
        let available = entry
            .enumerate_extensions()
            .map_err(|e| XrError::NoRuntime(e.to_string()))?;
        if !available.khr_vulkan_enable2 {
            return Err(XrError::MissingExtension("XR_KHR_vulkan_enable2"));
        }
        if !available.khr_convert_timespec_time {
            return Err(XrError::MissingExtension("XR_KHR_convert_timespec_time"));
        }
        let mut wanted = xr::ExtensionSet::default();
        wanted.khr_vulkan_enable2 = true;
        wanted.khr_convert_timespec_time = true;
        let instance = entry
            .create_instance(
                &xr::ApplicationInfo {
                    application_name: "lungdyn",
                    application_version: 1,
                    engine_name: "lungdyn",
                    engine_version: 1,
                    api_version: xr::Version::new(1, 0, 0),
                },
                &wanted,
                &[],
                &(),
            )
            .map_err(|e| XrError::NoRuntime(e.to_string()))?;
        let system = instance
            .system(xr::FormFactor::HEAD_MOUNTED_DISPLAY)
            .map_err(|e| XrError::NoHeadset(e.to_string()))?;
        let offered = call(
            "xrEnumerateEnvironmentBlendModes",
            instance.enumerate_environment_blend_modes(system, VIEW_TYPE),
        )?;
        let blend = crate::xr::choose_blend_mode(
            &offered
                .iter()
                .filter_map(|&m| blend_of(m))
                .collect::<Vec<_>>(),
        )
        .ok_or_else(|| XrError::NoBlendMode(format!("{offered:?}")))?;
        let views = call(
            "xrEnumerateViewConfigurationViews",
            instance.enumerate_view_configuration_views(system, VIEW_TYPE),
        )?;
        let v = views.first().ok_or(XrError::Call {
            what: "xrEnumerateViewConfigurationViews (no views)",
            result: xr::sys::Result::ERROR_VIEW_CONFIGURATION_TYPE_UNSUPPORTED,
        })?;
        let reqs = call(
            "xrGetVulkanGraphicsRequirements2KHR",
            instance.graphics_requirements::<xr::Vulkan>(system),
        )?;
        // The version `gpu` will make the instance for, checked against the runtime's range.
        let used = instance_version()?;
        let want = xr::Version::new(
            vk::api_version_major(used) as u16,
            vk::api_version_minor(used) as u16,
            0,
        );
        if want < reqs.min_api_version_supported
            || want.major() > reqs.max_api_version_supported.major()
        {
            return Err(XrError::VulkanVersion {
                min: reqs.min_api_version_supported.to_string(),
                max: reqs.max_api_version_supported.major(),
                used: want.to_string(),
            });
        }
        Ok(Self {
            instance,
            system,
            blend,
            eye_size: (
                v.recommended_image_rect_width,
                v.recommended_image_rect_height,
            ),
        })
    }

    /// The environment blend mode the frames are submitted with.
    pub fn blend(&self) -> BlendMode {
        self.blend
    }

    /// The GPU, created by the runtime (`XR_KHR_vulkan_enable2`) and wrapped into wgpu, and the
    /// Vulkan handles the session is bound to.
    pub fn gpu(&self) -> Result<(Gpu, xr::vulkan::SessionCreateInfo), XrError> {
        // SAFETY: every raw handle below is created here, from the entry and instance created just
        // before it, and handed to wgpu-hal (which then owns it) with the extensions and features
        // it was created with, as `from_raw` / `device_from_raw` require.
        unsafe {
            let vk_entry = ash::Entry::load().map_err(|e| vulkan("loading libvulkan", e))?;
            let version = instance_version_of(&vk_entry)?;
            let flags = wgpu::InstanceFlags::empty();
            let extensions = hal::vulkan::Instance::desired_extensions(&vk_entry, version, flags)
                .map_err(|e| vulkan("listing instance extensions", e))?;
            let names: Vec<*const std::ffi::c_char> =
                extensions.iter().map(|e| e.as_ptr()).collect();
            let app = vk::ApplicationInfo::default()
                .application_name(c"lungdyn")
                .api_version(version);
            let info = vk::InstanceCreateInfo::default()
                .application_info(&app)
                .enabled_extension_names(&names);
            #[allow(clippy::missing_transmute_annotations)]
            let gipa = std::mem::transmute(vk_entry.static_fn().get_instance_proc_addr);
            let raw_instance = call(
                "xrCreateVulkanInstanceKHR",
                self.instance.create_vulkan_instance(
                    self.system,
                    gipa,
                    &info as *const _ as *const _,
                ),
            )?
            .map_err(|r| vulkan("vkCreateInstance (through OpenXR)", vk::Result::from_raw(r)))?;
            let ash_instance = ash::Instance::load(
                vk_entry.static_fn(),
                vk::Instance::from_raw(raw_instance as _),
            );
            let hal_instance = hal::vulkan::Instance::from_raw(
                vk_entry.clone(),
                ash_instance.clone(),
                version,
                0,
                None,
                extensions,
                flags,
                wgpu::MemoryBudgetThresholds::default(),
                false,
                None,
            )
            .map_err(|e| vulkan("wrapping the instance", e))?;
            let phd = vk::PhysicalDevice::from_raw(call(
                "xrGetVulkanGraphicsDevice2KHR",
                self.instance
                    .vulkan_graphics_device(self.system, raw_instance),
            )? as _);
            let exposed = hal_instance.expose_adapter(phd).ok_or_else(|| {
                vulkan("exposing the adapter", "wgpu cannot use the headset's GPU")
            })?;
            let timestamps = exposed.features.contains(wgpu::Features::TIMESTAMP_QUERY);
            let features = if timestamps {
                wgpu::Features::TIMESTAMP_QUERY
            } else {
                wgpu::Features::empty()
            };
            let family = ash_instance
                .get_physical_device_queue_family_properties(phd)
                .iter()
                .position(|q| q.queue_flags.contains(vk::QueueFlags::GRAPHICS))
                .ok_or_else(|| vulkan("choosing a queue", "the GPU has no graphics queue"))?
                as u32;
            let device_extensions = exposed.adapter.required_device_extensions(features);
            let mut phd_features = exposed
                .adapter
                .physical_device_features(&device_extensions, features);
            let ext_names: Vec<*const std::ffi::c_char> =
                device_extensions.iter().map(|e| e.as_ptr()).collect();
            let priorities = [1.0f32];
            let queues = [vk::DeviceQueueCreateInfo::default()
                .queue_family_index(family)
                .queue_priorities(&priorities)];
            let device_info = phd_features.add_to_device_create(
                vk::DeviceCreateInfo::default()
                    .queue_create_infos(&queues)
                    .enabled_extension_names(&ext_names),
            );
            let raw_device = call(
                "xrCreateVulkanDeviceKHR",
                self.instance.create_vulkan_device(
                    self.system,
                    gipa,
                    phd.as_raw() as _,
                    &device_info as *const _ as *const _,
                ),
            )?
            .map_err(|r| vulkan("vkCreateDevice (through OpenXR)", vk::Result::from_raw(r)))?;
            let ash_device = ash::Device::load(
                ash_instance.fp_v1_0(),
                vk::Device::from_raw(raw_device as _),
            );
            let limits = exposed.capabilities.limits.clone();
            let open = exposed
                .adapter
                .device_from_raw(
                    ash_device,
                    None,
                    &device_extensions,
                    features,
                    &limits,
                    &wgpu::MemoryHints::Performance,
                    family,
                    0,
                )
                .map_err(|e| vulkan("wrapping the device", e))?;
            let instance = wgpu::Instance::from_hal::<hal::api::Vulkan>(hal_instance);
            let adapter = instance.create_adapter_from_hal(exposed);
            let (device, queue) = adapter
                .create_device_from_hal(
                    open,
                    &wgpu::DeviceDescriptor {
                        label: Some("lungdyn openxr"),
                        required_features: features,
                        required_limits: limits,
                        ..Default::default()
                    },
                )
                .map_err(|e| vulkan("opening the wgpu device", e))?;
            let info = adapter.get_info();
            let binding = xr::vulkan::SessionCreateInfo {
                instance: raw_instance,
                physical_device: phd.as_raw() as _,
                device: raw_device,
                queue_family_index: family,
                queue_index: 0,
            };
            Ok((
                Gpu {
                    instance,
                    adapter,
                    device,
                    queue,
                    info,
                    timestamps,
                },
                binding,
            ))
        }
    }
}

/// The OpenXR session as the renderer's [`crate::session::FrameOutput`].
pub struct XrOutput {
    // Dropped in this order: the swapchain and session before the instance.
    /// Each swapchain image wrapped into wgpu, with its view (made once: none per frame).
    images: Vec<(wgpu::Texture, wgpu::TextureView)>,
    swapchain: xr::Swapchain<xr::Vulkan>,
    stream: xr::FrameStream<xr::Vulkan>,
    waiter: xr::FrameWaiter,
    view_space: xr::Space,
    local_space: xr::Space,
    session: xr::Session<xr::Vulkan>,
    instance: xr::Instance,
    blend: xr::EnvironmentBlendMode,
    format: wgpu::TextureFormat,
    eye_size: (u32, u32),
    frame: Option<xr::FrameState>,
    /// The frame's predicted display time on CLOCK_MONOTONIC.
    display_ns: Option<u64>,
    views: Option<[xr::View; 2]>,
    acquired: Option<u32>,
    running: bool,
    /// The runtime ended the session (or lost it): the renderer stops, and needs not end it.
    exiting: bool,
    /// The renderer met an error of its own mid-run ([`Self::error`]): it stops, and still ends
    /// the session as OpenXR asks (the runtime did not).
    failed: bool,
    /// The first error the runtime reported mid-run; the renderer stops with it.
    pub error: Option<XrError>,
    events: xr::EventDataBuffer,
    blit: Option<PresentPass>,
    /// What the runtime was given, said when the renderer stops.
    pub stats: XrStats,
}

impl XrOutput {
    /// The session on `gpu` (made by [`XrSystem::gpu`]) and its swapchain, two eyes wide.
    pub fn new(
        system: XrSystem,
        gpu: &Gpu,
        binding: &xr::vulkan::SessionCreateInfo,
    ) -> Result<Self, XrError> {
        let XrSystem {
            instance,
            system,
            blend,
            eye_size,
        } = system;
        // SAFETY: `binding` holds the instance, physical device and device the runtime created for
        // this system in `XrSystem::gpu`, alive as long as `gpu`.
        let (session, waiter, stream) = call("xrCreateSession", unsafe {
            instance.create_session::<xr::Vulkan>(system, binding)
        })?;
        let view_space = call(
            "xrCreateReferenceSpace(VIEW)",
            session.create_reference_space(xr::ReferenceSpaceType::VIEW, xr::Posef::IDENTITY),
        )?;
        let local_space = call(
            "xrCreateReferenceSpace(LOCAL)",
            session.create_reference_space(xr::ReferenceSpaceType::LOCAL, xr::Posef::IDENTITY),
        )?;
        let offered: Vec<i64> = call(
            "xrEnumerateSwapchainFormats",
            session.enumerate_swapchain_formats(),
        )?
        .into_iter()
        .map(i64::from)
        .collect();
        let (vk_format, format) =
            crate::xr::choose_swapchain_format(&offered).ok_or(XrError::NoFormat(offered))?;
        let (w, h) = (eye_size.0 * 2, eye_size.1);
        let swapchain = call(
            "xrCreateSwapchain",
            session.create_swapchain(&xr::SwapchainCreateInfo {
                create_flags: xr::SwapchainCreateFlags::EMPTY,
                usage_flags: xr::SwapchainUsageFlags::COLOR_ATTACHMENT,
                format: vk_format as u32,
                sample_count: 1,
                width: w,
                height: h,
                face_count: 1,
                array_size: 1,
                mip_count: 1,
            }),
        )?;
        let raw_images = call("xrEnumerateSwapchainImages", swapchain.enumerate_images())?;
        let size = wgpu::Extent3d {
            width: w,
            height: h,
            depth_or_array_layers: 1,
        };
        let usage = wgpu::TextureUsages::RENDER_ATTACHMENT;
        let images = raw_images
            .into_iter()
            .map(|raw| {
                // SAFETY: the runtime's image of this swapchain, created with `size`, `format` and
                // these usages; it stays the runtime's (a no-op drop callback, external memory).
                unsafe {
                    let hal_device = gpu.device.as_hal::<hal::api::Vulkan>().ok_or_else(|| {
                        vulkan("wrapping a swapchain image", "not a Vulkan device")
                    })?;
                    let hal_texture = hal_device.texture_from_raw(
                        vk::Image::from_raw(raw),
                        &hal::TextureDescriptor {
                            label: Some("lungdyn openxr swapchain"),
                            size,
                            mip_level_count: 1,
                            sample_count: 1,
                            dimension: wgpu::TextureDimension::D2,
                            format,
                            usage: wgpu::TextureUses::COLOR_TARGET,
                            memory_flags: hal::MemoryFlags::empty(),
                            view_formats: Vec::new(),
                        },
                        Some(Box::new(|| {})),
                        hal::vulkan::TextureMemory::External,
                    );
                    Ok(gpu.device.create_texture_from_hal::<hal::api::Vulkan>(
                        hal_texture,
                        &wgpu::TextureDescriptor {
                            label: Some("lungdyn openxr swapchain"),
                            size,
                            mip_level_count: 1,
                            sample_count: 1,
                            dimension: wgpu::TextureDimension::D2,
                            format,
                            usage,
                            view_formats: &[],
                        },
                        wgpu::TextureUses::UNINITIALIZED,
                    ))
                    .map(|t| {
                        let view = t.create_view(&Default::default());
                        (t, view)
                    })
                }
            })
            .collect::<Result<Vec<_>, XrError>>()?;
        Ok(Self {
            images,
            swapchain,
            stream,
            waiter,
            view_space,
            local_space,
            session,
            instance,
            blend: xr_blend(blend),
            format,
            eye_size,
            frame: None,
            display_ns: None,
            views: None,
            acquired: None,
            running: false,
            exiting: false,
            failed: false,
            error: None,
            events: xr::EventDataBuffer::new(),
            blit: None,
            stats: XrStats::default(),
        })
    }

    /// Take the frames from `frame` (the renderer's offscreen image, two eyes wide, of
    /// `frame_size` pixels), drawn 1:1 into each swapchain image by a present pass.
    pub fn attach(
        &mut self,
        device: &wgpu::Device,
        frame: &wgpu::TextureView,
        frame_size: (u32, u32),
    ) {
        // An OpenXR swapchain offers no plain-bytes view: the exact copy reads and writes sRGB.
        self.blit = Some(PresentPass::new(
            device,
            frame,
            None,
            frame_size,
            self.format,
        ));
    }

    fn fail(&mut self, e: XrError) {
        if self.error.is_none() {
            self.error = Some(e);
        }
        self.failed = true;
    }

    /// Whether the frame loop stops: the runtime ended the session, or the renderer failed.
    pub fn should_stop(&self) -> bool {
        self.exiting || self.failed
    }

    /// Follow the session's state: begin when ready, end when stopping, stop when exiting.
    fn poll_events(&mut self) -> Result<(), XrError> {
        while let Some(event) = call("xrPollEvent", self.instance.poll_event(&mut self.events))? {
            match event {
                xr::Event::SessionStateChanged(e) => match e.state() {
                    xr::SessionState::READY => {
                        call("xrBeginSession", self.session.begin(VIEW_TYPE))?;
                        self.running = true;
                    }
                    xr::SessionState::STOPPING => {
                        call("xrEndSession", self.session.end())?;
                        self.running = false;
                    }
                    xr::SessionState::EXITING | xr::SessionState::LOSS_PENDING => {
                        self.running = false;
                        self.exiting = true;
                    }
                    _ => {}
                },
                xr::Event::InstanceLossPending(_) => self.exiting = true,
                _ => {}
            }
        }
        Ok(())
    }

    /// CLOCK_MONOTONIC now, as the runtime's XrTime (and the monotonic reading).
    fn clock(&self) -> Result<(XrClock, u64), XrError> {
        let now = transport::now_ns();
        let (tv_sec, tv_nsec) = crate::xr::ns_timespec(now);
        let ts = libc::timespec { tv_sec, tv_nsec };
        let convert = self
            .instance
            .exts()
            .khr_convert_timespec_time
            .as_ref()
            .ok_or(XrError::MissingExtension("XR_KHR_convert_timespec_time"))?;
        let mut t = xr::Time::from_nanos(0);
        // SAFETY: the extension was enabled on this instance; `ts` and `t` outlive the call.
        let r =
            unsafe { (convert.convert_timespec_time_to_time)(self.instance.as_raw(), &ts, &mut t) };
        if r.into_raw() < 0 {
            return Err(XrError::Call {
                what: "xrConvertTimespecTimeToTimeKHR",
                result: r,
            });
        }
        Ok((XrClock::from_pair(t.as_nanos(), now), now))
    }

    fn wait_frame(&mut self) -> Result<Option<u64>, XrError> {
        self.poll_events()?;
        self.frame = None;
        self.display_ns = None;
        if !self.running {
            return Ok(None);
        }
        let state = call("xrWaitFrame", self.waiter.wait())?;
        call("xrBeginFrame", self.stream.begin())?;
        self.frame = Some(state);
        let (clock, now) = self.clock()?;
        self.display_ns = clock.to_monotonic(state.predicted_display_time.as_nanos());
        if let Some(t) = self.display_ns {
            self.stats.waited(t, now);
        }
        Ok(self.display_ns)
    }

    fn locate(&mut self) -> Result<Option<crate::camera::HmdEyes>, XrError> {
        let Some(state) = self.frame.filter(|s| s.should_render) else {
            return Ok(None);
        };
        let t = state.predicted_display_time;
        self.views = None;
        let (Some([l, r]), Some(in_local)) = (
            self.locate_views(t, &self.view_space, "xrLocateViews(VIEW)")?,
            self.locate_views(t, &self.local_space, "xrLocateViews(LOCAL)")?,
        ) else {
            return Ok(None);
        };
        self.views = Some(in_local);
        let eye = |v: xr::View| XrEye {
            position_m: [v.pose.position.x, v.pose.position.y, v.pose.position.z],
            orientation: [
                v.pose.orientation.x,
                v.pose.orientation.y,
                v.pose.orientation.z,
                v.pose.orientation.w,
            ],
            fov: Fov {
                left: v.fov.angle_left,
                right: v.fov.angle_right,
                up: v.fov.angle_up,
                down: v.fov.angle_down,
            },
        };
        Ok(crate::xr::hmd_eyes(
            &[eye(l), eye(r)],
            self.eye_size.0,
            self.eye_size.1,
            NEAR_MM as f64,
            FAR_MM as f64,
        ))
    }

    /// Both eyes' views at `t` in `space`, `None` unless the runtime says both the orientation and
    /// the position are valid (lost tracking: the frame is ended without a layer, the eyes kept).
    /// Into an array on the stack: `Session::locate_views` allocates two vectors a call.
    fn locate_views(
        &self,
        t: xr::Time,
        space: &xr::Space,
        what: &'static str,
    ) -> Result<Option<[xr::View; 2]>, XrError> {
        let info = xr::sys::ViewLocateInfo {
            ty: xr::sys::ViewLocateInfo::TYPE,
            next: std::ptr::null(),
            view_configuration_type: VIEW_TYPE,
            display_time: t,
            space: space.as_raw(),
        };
        let mut state = xr::sys::ViewState {
            ty: xr::sys::ViewState::TYPE,
            next: std::ptr::null_mut(),
            view_state_flags: xr::ViewStateFlags::EMPTY,
        };
        let blank = xr::sys::View {
            ty: xr::sys::View::TYPE,
            next: std::ptr::null_mut(),
            pose: xr::Posef::IDENTITY,
            fov: xr::Fovf::default(),
        };
        let mut views = [blank; 2];
        let mut count = 0u32;
        // SAFETY: the session and space are alive; `info`, `state`, `count` and `views` (capacity
        // 2, the stereo configuration's count) outlive the call.
        let r = unsafe {
            (self.instance.fp().locate_views)(
                self.session.as_raw(),
                &info,
                &mut state,
                views.len() as u32,
                &mut count,
                views.as_mut_ptr(),
            )
        };
        if r.into_raw() < 0 {
            return Err(XrError::Call { what, result: r });
        }
        let valid = xr::ViewStateFlags::ORIENTATION_VALID | xr::ViewStateFlags::POSITION_VALID;
        if count != 2 || !state.view_state_flags.contains(valid) {
            return Ok(None);
        }
        Ok(Some(views.map(|v| xr::View {
            pose: v.pose,
            fov: v.fov,
        })))
    }

    fn acquire_and_copy(&mut self, encoder: &mut wgpu::CommandEncoder) -> Result<(), XrError> {
        if !self.frame.is_some_and(|s| s.should_render) || self.views.is_none() {
            return Ok(());
        }
        let Some(blit) = &self.blit else {
            return Ok(());
        };
        let index = call("xrAcquireSwapchainImage", self.swapchain.acquire_image())?;
        call(
            "xrWaitSwapchainImage",
            self.swapchain.wait_image(xr::Duration::INFINITE),
        )?;
        self.acquired = Some(index);
        let (image, view) = &self.images[index as usize];
        blit.encode(encoder, view, (image.width(), image.height()));
        Ok(())
    }

    fn end_frame(&mut self) -> Result<Option<u64>, XrError> {
        let Some(state) = self.frame.take() else {
            return Ok(None);
        };
        let t = state.predicted_display_time;
        let (Some(_), Some(views)) = (self.acquired.take(), self.views) else {
            call("xrEndFrame", self.stream.end(t, self.blend, &[]))?;
            self.stats
                .ended(self.display_ns, transport::now_ns(), false);
            return Ok(None);
        };
        call("xrReleaseSwapchainImage", self.swapchain.release_image())?;
        let (w, h) = (self.eye_size.0 as i32, self.eye_size.1 as i32);
        let rect = |x: i32| xr::Rect2Di {
            offset: xr::Offset2Di { x, y: 0 },
            extent: xr::Extent2Di {
                width: w,
                height: h,
            },
        };
        let view = |v: &xr::View, x: i32| {
            xr::CompositionLayerProjectionView::new()
                .pose(v.pose)
                .fov(v.fov)
                .sub_image(
                    xr::SwapchainSubImage::new()
                        .swapchain(&self.swapchain)
                        .image_array_index(0)
                        .image_rect(rect(x)),
                )
        };
        let projection_views = [view(&views[0], 0), view(&views[1], w)];
        let layer = xr::CompositionLayerProjection::new()
            .space(&self.local_space)
            .views(&projection_views);
        call("xrEndFrame", self.stream.end(t, self.blend, &[&layer]))?;
        let now = transport::now_ns();
        self.stats.ended(self.display_ns, now, true);
        Ok(Some(now))
    }

    /// Let go of the wgpu wrappers of the swapchain images and wait until wgpu has destroyed them
    /// (it does so lazily, once the GPU is done with them), so that no image view outlives the
    /// image the runtime destroys with the swapchain.
    pub fn release_images(&mut self, device: &wgpu::Device) {
        self.images.clear();
        self.blit = None;
        let _ = device.poll(wgpu::PollType::Wait {
            submission_index: None,
            timeout: None,
        });
    }

    /// End the session the way OpenXR asks (`xrRequestExitSession`, then `xrEndSession` when it
    /// reaches STOPPING, then EXITING), ending empty frames meanwhile; bounded, so a runtime that
    /// never gets there cannot hold the renderer's exit. A session that never ran, or that the
    /// runtime already ended, needs none of it.
    pub fn shutdown(&mut self) -> Result<(), XrError> {
        if !self.running || self.exiting {
            return Ok(());
        }
        // A frame begun but not ended (the loop stopped between wait and present) is ended first.
        if let Some(state) = self.frame.take() {
            if self.acquired.take().is_some() {
                call("xrReleaseSwapchainImage", self.swapchain.release_image())?;
            }
            call(
                "xrEndFrame",
                self.stream
                    .end(state.predicted_display_time, self.blend, &[]),
            )?;
        }
        call("xrRequestExitSession", self.session.request_exit())?;
        // Each pass ends one frame at most (one runtime frame period); bounded by time, not passes.
        let give_up = std::time::Instant::now() + std::time::Duration::from_secs(2);
        while std::time::Instant::now() < give_up {
            self.poll_events()?;
            if self.exiting {
                return Ok(());
            }
            if self.running {
                let state = call("xrWaitFrame", self.waiter.wait())?;
                call("xrBeginFrame", self.stream.begin())?;
                call(
                    "xrEndFrame",
                    self.stream
                        .end(state.predicted_display_time, self.blend, &[]),
                )?;
            } else {
                std::thread::sleep(std::time::Duration::from_millis(10));
            }
        }
        Err(XrError::Call {
            what: "xrRequestExitSession (the runtime never reached EXITING)",
            result: xr::sys::Result::ERROR_RUNTIME_FAILURE,
        })
    }
}

impl crate::session::FrameOutput for XrOutput {
    fn display_time_ns(&mut self) -> Option<u64> {
        match self.wait_frame() {
            Ok(t) => t,
            Err(e) => {
                self.fail(e);
                None
            }
        }
    }

    fn eyes(&mut self) -> Option<crate::camera::HmdEyes> {
        self.locate().unwrap_or_else(|e| {
            self.fail(e);
            None
        })
    }

    fn encode(&mut self, encoder: &mut wgpu::CommandEncoder) {
        if let Err(e) = self.acquire_and_copy(encoder) {
            self.fail(e);
        }
    }

    fn present(&mut self) -> Option<u64> {
        self.end_frame().unwrap_or_else(|e| {
            self.fail(e);
            None
        })
    }

    fn mode(&self) -> (u32, u32) {
        (ipc_types::present_mode::OPENXR, 0)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Here (and in CI) there is no OpenXR runtime: opening fails, naming the loader or the
    /// runtime to install, never panicking. (With a runtime present this checks nothing more than
    /// that opening it works.)
    #[test]
    fn without_a_runtime_opening_names_what_to_install() {
        std::env::set_var("XR_RUNTIME_JSON", "/nonexistent/openxr_runtime.json");
        match XrSystem::open() {
            Ok(_) => {}
            Err(e @ XrError::NoLoader(_)) => {
                let m = e.to_string();
                assert!(
                    m.contains("libopenxr-loader1") && m.contains("Monado"),
                    "{m}"
                );
            }
            Err(e @ XrError::NoRuntime(_)) => {
                let m = e.to_string();
                assert!(m.contains("Monado") && m.contains("XR_RUNTIME_JSON"), "{m}");
                // Debian 12 has no Monado package: the message must not send its users to one.
                assert!(
                    m.contains("bookworm")
                        && m.contains("from source")
                        && m.contains("xr_check.sh"),
                    "{m}"
                );
            }
            Err(e) => panic!("expected no loader or no runtime, got: {e}"),
        }
    }

    #[test]
    fn the_runtimes_blend_modes_map_both_ways() {
        for m in [
            BlendMode::Opaque,
            BlendMode::Additive,
            BlendMode::AlphaBlend,
        ] {
            assert_eq!(blend_of(xr_blend(m)), Some(m));
        }
        assert_eq!(blend_of(xr::EnvironmentBlendMode::from_raw(1000)), None);
    }
}
