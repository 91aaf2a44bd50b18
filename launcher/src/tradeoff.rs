//! `lungdyn bench tradeoff`: the speed/accuracy trade of the deformation modes, measured (seed ch. 7,
//! EQUATIONS.md §3).
//!
//! For generated left lungs of the requested sizes: every mode's error against eq. 7.1 (RMS and max,
//! mm and % of the largest displacement, at the reference volume over the 26-orientation set),
//! per-frame time on the CPU (the rayon pool, its thread count stated) and on the GPU (the
//! deformation pass alone, by timestamp queries, the adapter named), bake time and kernel size;
//! SH for 1..8 bands beside the exact basis, the precomputed field and eq. 7.1 itself; the
//! orientation methods (exact rotation, the seed's eq. 7.8–7.9 blend, a fixed supine force) over
//! roll and pitch sweeps; and stereo against mono frame rate. Writes `<out>.md`, `<out>.csv` and
//! `<out>.png` (+ `.svg`).

use std::path::{Path, PathBuf};
use std::time::Instant;

use anyhow::{bail, Context};
use glam::{DQuat, DVec3};
use serde::Serialize;

use lung_bake::kernel::{bake, BakeSettings};
use lung_bake::orient::{
    basis_error, orientation_set, reference_delta_ml, ErrorAccumulator, ErrorStats, Responses,
    ShProjection,
};
use lung_model::deform::modes::{CpuLung, ModeData};
use lung_model::mesh::{generate, Side};
use lung_model::orientation::{ForceWeights, SeedBlend, SUPINE_GRAVITY};

/// `--gpu`: whether the trade study times the GPU.
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub enum GpuUse {
    /// Time the GPU when an adapter opens; CPU figures only otherwise (said).
    Auto,
    /// CPU figures only.
    Off,
    /// Fail without a GPU adapter.
    Require,
}

/// Options of `lungdyn bench tradeoff`.
#[derive(Debug, Clone, clap::Args)]
pub struct TradeoffArgs {
    /// Output folder: writes tradeoff.md, tradeoff.csv, tradeoff.png and tradeoff.svg there.
    /// Default: a new folder out/tradeoff-N (never the committed docs; `--out docs` regenerates
    /// docs/tradeoff.*, see docs/PHYSICS.md).
    #[arg(long, value_name = "DIR")]
    pub out: Option<PathBuf>,
    /// Lung sizes (vertices of the generated left lung), comma-separated.
    #[arg(long, value_delimiter = ',', default_value = "10000,100000,400000")]
    pub sizes: Vec<usize>,
    /// Most SH bands to measure (1..8).
    #[arg(long, default_value_t = 8)]
    pub max_bands: usize,
    /// GPU timings: auto (when an adapter opens), off, or require (fail without one).
    #[arg(long, value_enum, default_value_t = GpuUse::Auto)]
    pub gpu: GpuUse,
    /// Timed repetitions per CPU/GPU figure (the median is reported).
    #[arg(long, default_value_t = 31)]
    pub runs: usize,
    /// Print the rows as one JSON object on stdout.
    #[arg(long)]
    pub json: bool,
}

/// One measured configuration.
#[derive(Debug, Clone, Serialize)]
pub struct Row {
    /// Vertices of the lung.
    pub vertices: usize,
    /// Mode.
    pub mode: String,
    /// SH bands (sh mode).
    pub bands: Option<usize>,
    /// Numbers per vertex the mode reads besides the position, in f32 equivalents (a 16-bit SH
    /// coefficient counts a half).
    pub floats_per_vertex: f64,
    /// Errors against eq. 7.1.
    pub error: ErrorStats,
    /// CPU time per frame, ms (median).
    pub cpu_ms: f64,
    /// GPU time of the deformation pass (with normals), ms (median); `None` without a GPU.
    pub gpu_ms: Option<f64>,
    /// Bake time of what this mode needs beyond the transfer rows (basis: the responses; sh: the
    /// projection and the fit), s; the transfer bake itself is in `transfer_bake_s`.
    pub mode_bake_s: f64,
    /// Transfer bake (pitcher–catcher, all rows), s.
    pub transfer_bake_s: f64,
    /// Kernel file size with this mode's data, MiB.
    pub kernel_mib: f64,
    /// SH: least-squares α.
    pub alpha: Option<f64>,
    /// SH: the largest displacement change of the run time's 16-bit storage of the coefficients
    /// (already inside `error`, which is of what is drawn), mm.
    pub quantisation_max_mm: Option<f64>,
    /// SH: how many times faster than eq. 7.1 on the CPU, both timed interleaved (run for run, so
    /// a slow phase of the machine falls on both): the median of the per-pair ratios.
    pub cpu_speedup_vs_direct: Option<f64>,
}

/// One orientation method over a sweep.
#[derive(Debug, Clone, Serialize)]
pub struct OrientationRow {
    /// Method.
    pub method: String,
    /// Sweep ("roll" or "pitch").
    pub sweep: String,
    /// Errors against eq. 7.1 with the true orientation's force, over the sweep.
    pub error: ErrorStats,
    /// Per angle (degrees) the RMS error, mm.
    pub series: Vec<(f64, f64)>,
}

/// What the trade study measured.
#[derive(Debug, Clone, Serialize)]
pub struct Tradeoff {
    /// Rows.
    pub rows: Vec<Row>,
    /// Orientation methods (on the smallest lung).
    pub orientation: Vec<OrientationRow>,
    /// CPU threads of the pool.
    pub cpu_threads: usize,
    /// CPU model.
    pub cpu: String,
    /// GPU adapter, if any.
    pub gpu: Option<String>,
    /// Stereo vs mono for every lung size at each eye size in [`STEREO_EYES`]: mono frame ms,
    /// stereo frame ms, ratio of rates (empty without a GPU).
    pub stereo: Vec<StereoFigure>,
    /// Copy bandwidth reference at the largest size: (bytes per vertex, ms, GB/s) for the basis
    /// mode's traffic.
    pub copy: Vec<CopyFigure>,
    /// The machine's 1-minute load average when the run started and when it ended
    /// (`/proc/loadavg`): timings from a busy machine are slower and noisier (errors are not).
    pub load_average: [Option<f64>; 2],
    /// The orientation limit's ratio the errors were measured at (scene `[engine]
    /// min_slope_ratio`'s default, EQUATIONS.md §3.3).
    pub min_slope_ratio: f64,
    /// Files written.
    pub files: Vec<String>,
}

/// A memory-copy reference for a mode's traffic.
#[derive(Debug, Clone, Serialize)]
pub struct CopyFigure {
    /// Vertices.
    pub vertices: usize,
    /// Mode.
    pub mode: String,
    /// Bytes per vertex the mode moves (reads + writes).
    pub bytes_per_vertex: usize,
    /// The mode's time, ms.
    pub mode_ms: f64,
    /// A plain copy of the same bytes, ms.
    pub copy_ms: f64,
    /// The mode's throughput as a fraction of the copy's (median of the per-pair ratios).
    pub fraction_of_copy: f64,
}

/// Stereo against mono.
#[derive(Debug, Clone, Serialize)]
pub struct StereoFigure {
    /// Vertices drawn.
    pub vertices: usize,
    /// Eye image size.
    pub eye: (u32, u32),
    /// Mono frame (deform + one eye), GPU ms.
    pub mono_ms: f64,
    /// Stereo frame (deform once + two eyes), GPU ms.
    pub stereo_ms: f64,
    /// Deformation pass alone, GPU ms.
    pub deform_ms: f64,
    /// Stereo frame rate / mono frame rate (median of the ratios of frames timed alternately).
    pub rate_ratio: f64,
}

fn median(runs: usize, mut f: impl FnMut()) -> f64 {
    f();
    let mut t: Vec<f64> = (0..runs.max(1))
        .map(|_| {
            let s = Instant::now();
            f();
            s.elapsed().as_secs_f64()
        })
        .collect();
    t.sort_by(f64::total_cmp);
    t[t.len() / 2]
}

/// Medians of `a` and `b` timed alternately (a, b, a, b, …), and the median of the per-pair ratios
/// `b/a`: a slow phase of a shared machine falls on both halves of a pair, so the ratio holds where
/// a ratio of the two medians (taken over minutes of changing load) would not.
fn median_pair(runs: usize, mut a: impl FnMut(), mut b: impl FnMut()) -> (f64, f64, f64) {
    a();
    b();
    let (mut ta, mut tb) = (Vec::new(), Vec::new());
    for _ in 0..runs.max(1) {
        let s = Instant::now();
        a();
        ta.push(s.elapsed().as_secs_f64());
        let s = Instant::now();
        b();
        tb.push(s.elapsed().as_secs_f64());
    }
    let ratios = ta.iter().zip(&tb).map(|(a, b)| b / a).collect();
    (
        median_of(ta).unwrap_or(f64::NAN),
        median_of(tb).unwrap_or(f64::NAN),
        median_of(ratios).unwrap_or(f64::NAN),
    )
}

/// `lung`'s CPU pass against a one-thread copy of the bytes it moves (`bytes` per vertex), timed
/// alternately ([`median_pair`]).
fn copy_figure(
    mode: &str,
    bytes: usize,
    runs: usize,
    lung: &mut CpuLung,
    scale: f32,
    coeffs: &[f32],
    outputs: &mut [[f32; 3]],
) -> CopyFigure {
    let vertices = lung.len();
    let half = vertices * bytes / 2;
    let src = vec![1u8; half];
    let mut dst = vec![0u8; half];
    let (ms, copy_ms, copy_over_mode) = median_pair(
        runs,
        || {
            lung.deform_into(scale, coeffs, [0.0; 3], outputs)
                .expect("coefficient count");
            std::hint::black_box(&*outputs);
        },
        || {
            dst.copy_from_slice(std::hint::black_box(&src));
            std::hint::black_box(&dst);
        },
    );
    CopyFigure {
        vertices,
        mode: mode.into(),
        bytes_per_vertex: bytes,
        mode_ms: ms * 1e3,
        copy_ms: copy_ms * 1e3,
        fraction_of_copy: copy_over_mode,
    }
}

fn median_of(mut v: Vec<f64>) -> Option<f64> {
    if v.is_empty() {
        return None;
    }
    v.sort_by(f64::total_cmp);
    Some(v[v.len() / 2])
}

fn cpu_model() -> String {
    std::fs::read_to_string("/proc/cpuinfo")
        .ok()
        .and_then(|s| {
            s.lines()
                .find(|l| l.starts_with("model name"))
                .and_then(|l| l.split(':').nth(1))
                .map(|m| m.trim().to_string())
        })
        .unwrap_or_else(|| "unknown CPU".into())
}

/// The SH force coefficients `F_k = α·Σ_a w_a·P_ak` for `n` bands.
fn sh_coeffs(alpha: f64, projection: &[f64], w: &ForceWeights) -> Vec<f32> {
    let n2 = projection.len() / 4;
    (0..n2)
        .map(|k| (alpha * (0..4).map(|a| w[a] * projection[a * n2 + k]).sum::<f64>()) as f32)
        .collect()
}

/// What the study gathers over the lung sizes.
#[derive(Default)]
struct Gathered {
    rows: Vec<Row>,
    copies: Vec<CopyFigure>,
    orientation: Vec<OrientationRow>,
    stereo: Vec<StereoFigure>,
}

/// Run the trade study.
pub fn run(args: &TradeoffArgs) -> anyhow::Result<Tradeoff> {
    let load_at_start = lungdyn_remote::measure::load_average();
    let out_dir = check_args(args)?;
    let gpu = open_gpu(args.gpu)?;
    let gpu_name = gpu.as_ref().map(|g| g.describe());
    let settings = {
        let mut s = BakeSettings::default_for(Side::Left);
        s.sh_bands = 0;
        s
    };
    let mut gathered = Gathered::default();
    let mut sizes = args.sizes.clone();
    sizes.sort_unstable();
    for (size_index, &n) in sizes.iter().enumerate() {
        let bench = SizeBench::bake(n, &settings, args.runs, gpu.as_ref())?;
        bench.measure(args.max_bands, size_index == 0, &mut gathered)?;
        eprintln!(
            "lungdyn: {n} vertices done ({} CPU threads{})",
            rayon::current_num_threads(),
            gpu_name
                .as_deref()
                .map(|g| format!(", GPU {g}"))
                .unwrap_or_default()
        );
    }
    let mut result = Tradeoff {
        rows: gathered.rows,
        orientation: gathered.orientation,
        cpu_threads: rayon::current_num_threads(),
        cpu: cpu_model(),
        gpu: gpu_name,
        stereo: gathered.stereo,
        copy: gathered.copies,
        load_average: [load_at_start, lungdyn_remote::measure::load_average()],
        min_slope_ratio: lung_model::orientation::DEFAULT_MIN_SLOPE_RATIO,
        files: Vec::new(),
    };
    result.files = write_outputs(&out_dir.join("tradeoff"), &result)?;
    Ok(result)
}

/// The options checked and the output folder made (every output refused now if it is a device,
/// FIFO or folder, not after minutes of measuring with some of the four already written).
fn check_args(args: &TradeoffArgs) -> anyhow::Result<PathBuf> {
    if args.sizes.is_empty()
        || args
            .sizes
            .iter()
            .any(|&n| !(generate::MIN_VERTICES..=generate::MAX_VERTICES).contains(&n))
    {
        bail!(
            "--sizes {:?}: each must be within {}..{} vertices",
            args.sizes,
            generate::MIN_VERTICES,
            generate::MAX_VERTICES
        );
    }
    if !(1..=lung_model::kernel::MAX_RUNTIME_BANDS as usize).contains(&args.max_bands) {
        bail!("--max-bands {} must be within 1..8", args.max_bands);
    }
    if !(1..=1001).contains(&args.runs) {
        bail!("--runs {} must be within 1..1001", args.runs);
    }
    let out_dir = match &args.out {
        Some(d) => d.clone(),
        None => crate::outputs::new_folder(Path::new("out"), "tradeoff")?,
    };
    crate::outputs::check_writable(&out_dir)?;
    for ext in ["md", "csv", "png", "svg"] {
        outfile::check(&out_dir.join(format!("tradeoff.{ext}")))?;
    }
    eprintln!(
        "lungdyn bench tradeoff: writing {}",
        out_dir.join("tradeoff.{md,csv,png,svg}").display()
    );
    Ok(out_dir)
}

/// The GPU `--gpu` asks for: none when off, or when `auto` finds no adapter (said).
fn open_gpu(want: GpuUse) -> anyhow::Result<Option<renderer::gpu::Gpu>> {
    Ok(match want {
        GpuUse::Off => None,
        want => match renderer::gpu::Gpu::new() {
            Ok(g) => Some(g),
            Err(e) if want == GpuUse::Require => return Err(e.into()),
            Err(e) => {
                eprintln!("lungdyn: no GPU ({e}); CPU figures only");
                None
            }
        },
    })
}

/// One lung size baked, and what every mode's measurement of it shares: the exact responses and
/// volume forms, the reference volume change and the supine scale the modes are timed at.
struct SizeBench<'g> {
    n: usize,
    side: Side,
    runs: usize,
    gpu: Option<&'g renderer::gpu::Gpu>,
    k: lung_bake::kernel::Kernel,
    c789: [f64; 3],
    orientations: Vec<DVec3>,
    transfer_bake_s: f64,
    basis_bake_s: f64,
    /// What every kernel holds (header, metadata, the ch. 6 sections), bytes, less the basis
    /// section, counted per mode.
    base_bytes: f64,
    responses: Responses,
    exact_forms: lung_model::deform::modes::VolumeForms,
    delta_ml: f64,
    supine: ForceWeights,
    s_supine: f32,
    /// The kernel's directions times its force scale.
    kd: Vec<[f32; 3]>,
}

impl<'g> SizeBench<'g> {
    /// Bake the generated left lung of `n` vertices and its exact responses.
    fn bake(
        n: usize,
        settings: &BakeSettings,
        runs: usize,
        gpu: Option<&'g renderer::gpu::Gpu>,
    ) -> anyhow::Result<Self> {
        let side = Side::Left;
        let c = settings.motion.c;
        let c789 = [c[6], c[7], c[8]];
        eprintln!("lungdyn: {n} vertices: baking the transfer rows ...");
        let t = Instant::now();
        let k = bake(side, generate::lung(side, n)?, settings, &|_| {})?;
        let transfer_bake_s = t.elapsed().as_secs_f64();
        let v = k.mesh.positions.len();
        let base_bytes = {
            let dir = std::env::temp_dir().join(format!("lungdyn-tradeoff-{}", std::process::id()));
            std::fs::create_dir_all(&dir)?;
            let path = dir.join("k.kernel");
            let len = k.write(&path)?;
            let _ = std::fs::remove_file(&path);
            len as f64 - (v * 16) as f64
        };
        let t = Instant::now();
        let mut responses = k.responses();
        let exact_forms = responses.forms_of(&k.mesh, &responses.g);
        responses.set_limit(&exact_forms);
        let basis_bake_s = t.elapsed().as_secs_f64();
        let delta_ml = reference_delta_ml(k.meta.start_volume_ml);
        let supine = responses.weights(SUPINE_GRAVITY);
        let s_supine = exact_forms.cubic(&supine).solve_delta(delta_ml * 1000.0) as f32;
        let kd = k
            .directions
            .iter()
            .map(|d| d.map(|x| x * k.meta.force_scale as f32))
            .collect();
        Ok(Self {
            n,
            side,
            runs,
            gpu,
            k,
            c789,
            orientations: orientation_set(),
            transfer_bake_s,
            basis_bake_s,
            base_bytes,
            responses,
            exact_forms,
            delta_ml,
            supine,
            s_supine,
            kd,
        })
    }

    /// The kernel's size with `extra_bytes` of a mode's own sections, MiB.
    fn mib(&self, extra_bytes: f64) -> f64 {
        (self.base_bytes + extra_bytes) / 1048576.0
    }

    /// `lung`'s CPU pass at the supine scale, median ms.
    fn time_cpu(&self, lung: &mut CpuLung, coeffs: &[f32], out: &mut [[f32; 3]]) -> f64 {
        median(self.runs, || {
            lung.deform_into(self.s_supine, coeffs, [0.0; 3], out)
                .expect("coefficient count");
            std::hint::black_box(&out);
        }) * 1e3
    }

    /// `lung`'s GPU deformation pass by timestamp queries, median ms; none without a GPU (or when
    /// the renderer cannot take this lung, said).
    fn time_gpu(&self, lung: &CpuLung, coeffs: &[f32]) -> anyhow::Result<Option<f64>> {
        let Some(gpu) = self.gpu else { return Ok(None) };
        let mut scene = lung_model::scene::RenderScene::default();
        scene.width = 64;
        scene.height = 64;
        let render_lung = renderer::RenderLung {
            side: self.side,
            kernel_id: 0,
            lung: lung.clone(),
            tumour: None,
            lobes: None,
        };
        let r = match renderer::LungRenderer::new(gpu, &scene, &[render_lung]) {
            Ok(r) => r,
            Err(e) => {
                eprintln!("lungdyn: {} vertices, {}: {e}", self.n, lung.data.mode());
                return Ok(None);
            }
        };
        let mut state = renderer::DrawState {
            deform_scale: [0.0; 2],
            offset_mm: [[0.0; 3]; 2],
            collapse: [0.0; 2],
            hilum_mm: [[0.0; 3]; 2],
            coeffs: [[0.0; ipc_types::MAX_COEFFS]; 2],
            patient: ipc_types::Pose::IDENTITY,
            hmd: ipc_types::Pose::IDENTITY,
            pose_warning: Default::default(),
        };
        let slot = self.side.index();
        state.deform_scale[slot] = self.s_supine;
        state.coeffs[slot][..coeffs.len()].copy_from_slice(coeffs);
        let _ = r.time_deform(gpu, &state);
        let times: Vec<f64> = (0..self.runs)
            .filter_map(|_| r.time_deform(gpu, &state))
            .map(|ns| ns as f64 / 1e6)
            .collect();
        Ok(median_of(times))
    }

    /// A row of `mode` with what every row of this size shares (no bands, no SH figures).
    #[allow(clippy::too_many_arguments)]
    fn row(
        &self,
        mode: &str,
        floats_per_vertex: f64,
        error: ErrorStats,
        cpu_ms: f64,
        gpu_ms: Option<f64>,
        mode_bake_s: f64,
        extra_bytes: f64,
    ) -> Row {
        Row {
            vertices: self.k.mesh.positions.len(),
            mode: mode.into(),
            bands: None,
            floats_per_vertex,
            error,
            cpu_ms,
            gpu_ms,
            mode_bake_s,
            transfer_bake_s: self.transfer_bake_s,
            kernel_mib: self.mib(extra_bytes),
            alpha: None,
            quantisation_max_mm: None,
            cpu_speedup_vs_direct: None,
        }
    }

    /// The precomputed field's error over the orientation set (it ignores them: the supine
    /// field at the supine scale against each orientation's exact displacement).
    fn precomputed_error(&self) -> ErrorStats {
        let (r, forms, delta) = (&self.responses, &self.exact_forms, self.delta_ml * 1000.0);
        let mut acc = ErrorAccumulator::default();
        let supine_force = r.force(&self.supine);
        for &g in &self.orientations {
            let w = r.weights(g);
            let s_ref = forms.cubic(&w).solve_delta(delta);
            let s_pre = forms.cubic(&self.supine).solve_delta(delta);
            acc.add(&r.kd, s_ref, &r.force(&w), s_pre, &supine_force);
        }
        acc.stats()
    }

    /// Every mode of this size: precomputed, basis, eq. 7.1 itself, SH for 1..`max_bands` bands;
    /// the copy references; the orientation methods on the first size; stereo against mono.
    fn measure(&self, max_bands: usize, first_size: bool, g: &mut Gathered) -> anyhow::Result<()> {
        let (k, n, v) = (&self.k, self.n, self.k.mesh.positions.len());
        let mut outputs = vec![[0.0f32; 3]; v];
        let mesh = k.mesh.clone();
        eprintln!("lungdyn: {n} vertices: precomputed, basis, eq. 7.1 ...");
        let mut pre = CpuLung::new(
            mesh.clone(),
            Vec::new(),
            ModeData::Precomputed {
                unit: k.unit_displacement.clone(),
            },
        );
        let pre_ms = self.time_cpu(&mut pre, &[], &mut outputs);
        let pre_gpu = self.time_gpu(&pre, &[])?;
        let pre_err = self.precomputed_error();
        g.rows
            .push(self.row("precomputed", 3.0, pre_err, pre_ms, pre_gpu, 0.0, 0.0));
        let basis = self.responses.stored();
        let basis_err = basis_error(
            &k.transfer,
            &self.responses,
            &basis,
            &k.directions,
            k.meta.force_scale,
            &self.exact_forms,
            &self.orientations,
            self.delta_ml,
        );
        let w32 = self.supine.map(|x| x as f32);
        let mut basis_lung =
            CpuLung::new(mesh.clone(), self.kd.clone(), ModeData::Basis { g: basis });
        let basis_ms = self.time_cpu(&mut basis_lung, &w32, &mut outputs);
        let basis_gpu = self.time_gpu(&basis_lung, &w32)?;
        g.rows.push(self.row(
            "basis",
            7.0,
            basis_err,
            basis_ms,
            basis_gpu,
            self.basis_bake_s,
            (v * 16) as f64,
        ));
        // Memory-copy references of the same traffic, same run, timed alternately with the mode
        // (a slow phase of a shared machine falls on both).
        for (mode, bytes) in [("precomputed", 36usize), ("basis", 52)] {
            let (lung, coeffs): (&mut CpuLung, &[f32]) = if mode == "basis" {
                (&mut basis_lung, &w32)
            } else {
                (&mut pre, &[])
            };
            g.copies.push(copy_figure(
                mode,
                bytes,
                self.runs,
                lung,
                self.s_supine,
                coeffs,
                &mut outputs,
            ));
        }
        // Eq. 7.1 itself: the reference (its error is the f32 evaluation's round-off).
        let mut direct = CpuLung::new(
            mesh.clone(),
            self.kd.clone(),
            ModeData::Direct {
                columns: k.transfer.transposed(),
                // The basis functions the bake used (the fitted supine force first, if any).
                nhat: self
                    .responses
                    .nhat
                    .iter()
                    .map(|n| n.map(|v| v as f32))
                    .collect(),
                force: vec![0.0; v],
                elastostatic: vec![0.0; v],
            },
        );
        let direct_ms = self.time_cpu(&mut direct, &w32, &mut outputs);
        let direct_gpu = self.time_gpu(&direct, &w32)?;
        g.rows.push(self.row(
            "direct (eq. 7.1)",
            2.0 * k.meta.transfer.mean_row_nnz + 7.0,
            ErrorStats::default(),
            direct_ms,
            direct_gpu,
            0.0,
            0.0,
        ));
        self.sh_rows(max_bands, &mut direct, &w32, &mut outputs, g)?;
        // Orientation methods on the smallest lung; stereo on every lung, at a typical and at a
        // tiny eye size (where drawing costs next to nothing even on a software rasteriser).
        if first_size {
            g.orientation =
                orientation_methods(&self.responses, &self.exact_forms, self.c789, self.delta_ml);
        }
        if let Some(gpu) = self.gpu {
            for eye in STEREO_EYES {
                eprintln!(
                    "lungdyn: {n} vertices: stereo against mono, {}×{} per eye ...",
                    eye.0, eye.1
                );
                g.stereo.push(stereo_figure(
                    gpu,
                    &basis_lung,
                    self.s_supine,
                    &w32,
                    self.runs,
                    eye,
                )?);
            }
        }
        Ok(())
    }

    /// SH with 1..`max_bands` bands, each projected and fitted on its own (bake time per band
    /// count), each timed against eq. 7.1 (`direct`, still loaded) for its speed-up; the seed's 16
    /// coefficients also against a copy of their bytes.
    fn sh_rows(
        &self,
        max_bands: usize,
        direct: &mut CpuLung,
        w32: &[f32; 4],
        outputs: &mut [[f32; 3]],
        g: &mut Gathered,
    ) -> anyhow::Result<()> {
        let (k, n, v) = (&self.k, self.n, self.k.mesh.positions.len());
        let mesh = &k.mesh;
        let columns = k.transfer.transposed();
        let mut direct_out = vec![[0.0f32; 3]; v];
        for bands in 1..=max_bands {
            eprintln!("lungdyn: {n} vertices: SH with {bands} bands ...");
            let t = Instant::now();
            let projection = ShProjection::compute(mesh, &columns, &self.responses.nhat, bands)?;
            let fit = projection.fit(
                bands,
                mesh,
                &self.responses,
                &self.exact_forms,
                &self.orientations,
                self.delta_ml,
            );
            let sh_bake_s = t.elapsed().as_secs_f64();
            let coeffs = sh_coeffs(fit.alpha, &projection.projection(bands), &self.supine);
            let mut lung = CpuLung::new(
                mesh.clone(),
                self.kd.clone(),
                ModeData::Sh {
                    t: projection.quantised(bands),
                },
            );
            let ms = self.time_cpu(&mut lung, &coeffs, outputs);
            let (_, _, direct_over_sh) = median_pair(
                self.runs,
                || {
                    lung.deform_into(self.s_supine, &coeffs, [0.0; 3], outputs)
                        .expect("coefficient count");
                    std::hint::black_box(&*outputs);
                },
                || {
                    direct
                        .deform_into(self.s_supine, w32, [0.0; 3], &mut direct_out)
                        .expect("coefficient count");
                    std::hint::black_box(&direct_out);
                },
            );
            if bands == 4 {
                // The seed's 16 coefficients against a copy of their bytes: p, 16-bit T and k·d
                // read (12 + 32 + 12 B), the position written (12 B).
                let ModeData::Sh { t } = &lung.data else {
                    unreachable!("an SH lung")
                };
                let bytes = 12 + t.bytes_per_vertex() + 12 + 12;
                g.copies.push(copy_figure(
                    "sh, 16 coefficients",
                    bytes,
                    self.runs,
                    &mut lung,
                    self.s_supine,
                    &coeffs,
                    outputs,
                ));
            }
            let gpu_ms = self.time_gpu(&lung, &coeffs)?;
            g.rows.push(Row {
                bands: Some(bands),
                alpha: Some(fit.alpha),
                quantisation_max_mm: Some(fit.quantisation_max_mm),
                cpu_speedup_vs_direct: Some(direct_over_sh),
                // 16-bit coefficients: half a float each.
                ..self.row(
                    "sh",
                    (bands * bands) as f64 / 2.0 + 3.0,
                    fit.error,
                    ms,
                    gpu_ms,
                    sh_bake_s,
                    (v * 16 + v * bands * bands * 4) as f64,
                )
            });
        }
        Ok(())
    }
}

/// The orientation methods over roll and pitch sweeps, against eq. 7.1 with the true force.
fn orientation_methods(
    responses: &Responses,
    forms: &lung_model::deform::modes::VolumeForms,
    c789: [f64; 3],
    delta_ml: f64,
) -> Vec<OrientationRow> {
    let seed = SeedBlend::new(c789, responses.side);
    let limit = responses.limit;
    let limited = |w: ForceWeights| match &limit {
        Some(l) => l.apply(w).0,
        None => w,
    };
    let sweeps: [(&str, fn(f64) -> DQuat); 2] = [
        ("roll", |a| DQuat::from_rotation_z(a)),
        ("pitch", |a| DQuat::from_rotation_x(a)),
    ];
    let methods: [(&str, &dyn Fn(DVec3) -> ForceWeights); 3] = [
        ("exact rotation", &|g| responses.weights(g)),
        ("seed eq. 7.8-7.9", &|g| {
            limited(responses.as_drawn(seed.weights(g)))
        }),
        ("fixed (supine)", &|_| responses.weights(SUPINE_GRAVITY)),
    ];
    let mut out = Vec::new();
    for (sweep, turn) in sweeps {
        let (lo, hi) = if sweep == "roll" {
            (-180, 180)
        } else {
            (-90, 90)
        };
        for (name, method) in &methods {
            let mut acc = ErrorAccumulator::default();
            let mut series = Vec::new();
            for deg in (lo..=hi).step_by(15) {
                // Body-frame gravity of a supine patient turned by `deg` about the long axis
                // (roll: body Z) or the left-right axis (pitch: body X).
                let g = turn((deg as f64).to_radians()) * SUPINE_GRAVITY;
                let w_true = responses.weights(g);
                let w = method(g);
                let s_ref = forms.cubic(&w_true).solve_delta(delta_ml * 1000.0);
                let s = forms.cubic(&w).solve_delta(delta_ml * 1000.0);
                let mut one = ErrorAccumulator::default();
                let (d_ref, d) = (responses.force(&w_true), responses.force(&w));
                one.add(&responses.kd, s_ref, &d_ref, s, &d);
                acc.add(&responses.kd, s_ref, &d_ref, s, &d);
                series.push((deg as f64, one.stats().rms_mm));
            }
            out.push(OrientationRow {
                method: name.to_string(),
                sweep: sweep.into(),
                error: acc.stats(),
                series,
            });
        }
    }
    out
}

/// Eye image sizes of the stereo figures: a typical preview size, and a tiny one at which the draw
/// costs next to nothing, so the frame is the deformation pass plus fixed costs (the case the
/// "stereo costs the deformation nothing extra" claim is about).
pub const STEREO_EYES: [(u32, u32); 2] = [(320, 240), (32, 24)];

fn stereo_figure(
    gpu: &renderer::gpu::Gpu,
    lung: &CpuLung,
    scale: f32,
    w: &[f32; 4],
    runs: usize,
    eye: (u32, u32),
) -> anyhow::Result<StereoFigure> {
    let renderer = |stereo: bool| -> anyhow::Result<renderer::LungRenderer> {
        let mut scene = lung_model::scene::RenderScene::default();
        scene.width = eye.0;
        scene.height = eye.1;
        scene.stereo = stereo;
        Ok(renderer::LungRenderer::new(
            gpu,
            &scene,
            &[renderer::RenderLung {
                side: Side::Left,
                kernel_id: 0,
                lung: lung.clone(),
                tumour: None,
                lobes: None,
            }],
        )?)
    };
    let (mono, stereo) = (renderer(false)?, renderer(true)?);
    let mut state = renderer::DrawState {
        deform_scale: [0.0, scale],
        offset_mm: [[0.0; 3]; 2],
        collapse: [0.0; 2],
        hilum_mm: [[0.0; 3]; 2],
        coeffs: [[0.0; ipc_types::MAX_COEFFS]; 2],
        patient: ipc_types::Pose::IDENTITY,
        hmd: ipc_types::Pose {
            quat: [0.0, 0.0, 0.0, 1.0],
            translation_mm: [0.0, 0.0, 900.0],
            _pad: 0,
        },
        pose_warning: Default::default(),
    };
    state.coeffs[1][..4].copy_from_slice(w);
    let ms = |r: &renderer::LungRenderer| {
        r.render(gpu, &state, false)
            .gpu_ns
            .map(|ns| ns as f64 / 1e6)
    };
    // Mono and stereo frames alternately, so a slow phase of the machine falls on both; the rate
    // ratio is the median of the per-pair ratios.
    let (_, _) = (ms(&mono), ms(&stereo));
    let (mut m, mut st, mut ratio) = (Vec::new(), Vec::new(), Vec::new());
    for _ in 0..runs.max(1) {
        if let (Some(a), Some(b)) = (ms(&mono), ms(&stereo)) {
            m.push(a);
            st.push(b);
            ratio.push(a / b);
        }
    }
    let deform: Vec<f64> = (0..runs)
        .filter_map(|_| mono.time_deform(gpu, &state))
        .map(|ns| ns as f64 / 1e6)
        .collect();
    Ok(StereoFigure {
        vertices: lung.len(),
        eye,
        mono_ms: median_of(m).unwrap_or(f64::NAN),
        stereo_ms: median_of(st).unwrap_or(f64::NAN),
        deform_ms: median_of(deform).unwrap_or(f64::NAN),
        rate_ratio: median_of(ratio).unwrap_or(f64::NAN),
    })
}

fn fmt_opt(v: Option<f64>, digits: usize) -> String {
    v.filter(|x| x.is_finite())
        .map(|x| format!("{x:.digits$}"))
        .unwrap_or_else(|| "–".into())
}

fn markdown(t: &Tradeoff, stem: &str) -> String {
    use std::fmt::Write;
    let mut s = String::new();
    let _ = writeln!(s, "# The deformation modes: speed against accuracy\n");
    let _ = writeln!(
        s,
        "Written by `lungdyn bench tradeoff` (see `launcher/src/tradeoff.rs`); regenerate with \
         `cargo run --release --bin lungdyn -- bench tradeoff --out docs`. Generated left \
         lung, Table 6.1 constants, default elasticity and tolerance. Errors are displacements \
         against eq. 7.1 evaluated in f64, at the reference volume (+250 ml, a tidal breath's share \
         of one lung) over 26 orientations (supine, prone, both lateral decubitus postures, upright, \
         head-down and 20 seeded random ones), each mode's scale solved from its own volume forms \
         (what is drawn). CPU: {} with a rayon pool of {} threads; GPU: {} (the deformation pass \
         with the normals, by timestamp queries). Medians of repeated runs; the machine's \
         1-minute load average was {} at the start and {} at the end (a busy machine's timings are \
         slower and noisier; the errors do not depend on it). Turned postures' forces are limited \
         at a volume slope of {} of supine's (`[engine] min_slope_ratio`, EQUATIONS.md §3.3).\n",
        t.cpu,
        t.cpu_threads,
        t.gpu.as_deref().unwrap_or("none on this machine"),
        fmt_opt(t.load_average[0], 2),
        fmt_opt(t.load_average[1], 2),
        t.min_slope_ratio
    );
    let _ = writeln!(s, "![trade-off plot]({stem}.png)\n");
    let _ = writeln!(
        s,
        "| vertices | mode | coefficients | RMS mm | max mm | RMS % | max % | 16-bit storage's share, max mm | CPU ms/frame | × faster than eq. 7.1 (CPU, interleaved) | GPU ms/frame | mode bake s | kernel MiB | α |\n|---|---|---|---|---|---|---|---|---|---|---|---|---|---|"
    );
    for r in &t.rows {
        let _ = writeln!(
            s,
            "| {} | {} | {} | {:.3} | {:.3} | {:.2} | {:.2} | {} | {:.3} | {} | {} | {:.2} | {:.1} | {} |",
            r.vertices,
            r.mode,
            r.bands
                .map(|b| format!("{} ({} bands)", b * b, b))
                .unwrap_or_else(|| "–".into()),
            r.error.rms_mm,
            r.error.max_mm,
            r.error.rms_percent,
            r.error.max_percent,
            fmt_opt(r.quantisation_max_mm, 4),
            r.cpu_ms,
            fmt_opt(r.cpu_speedup_vs_direct, 1),
            fmt_opt(r.gpu_ms, 3),
            r.mode_bake_s,
            r.kernel_mib,
            fmt_opt(r.alpha, 4)
        );
    }
    let _ = writeln!(
        s,
        "\nThe transfer bake (pitcher–catcher, every row) itself: {}.\n",
        {
            let mut seen = Vec::new();
            for r in &t.rows {
                if !seen.iter().any(|(v, _)| *v == r.vertices) {
                    seen.push((r.vertices, r.transfer_bake_s));
                }
            }
            seen.iter()
                .map(|(v, b)| format!("{v} vertices {b:.1} s"))
                .collect::<Vec<_>>()
                .join(", ")
        }
    );
    bandwidth_section(&mut s, t);
    orientation_section(&mut s, t);
    stereo_section(&mut s, t);
    seed_section(&mut s, t);
    s
}

/// The report's memory-bandwidth section.
fn bandwidth_section(s: &mut String, t: &Tradeoff) {
    use std::fmt::Write;
    let _ = writeln!(
        s,
        "## Memory bandwidth (CPU, same run)\n\nThe mode and a one-thread copy of the same bytes, timed \
         alternately (mode, copy, mode, …) so a slow phase of a shared machine falls on both; the \
         last column is the median of the per-pair ratios. The speed-ups over eq. 7.1 above are \
         taken the same way.\n"
    );
    let _ = writeln!(
        s,
        "| vertices | mode | bytes/vertex | mode ms | copy of the same bytes ms | mode throughput / copy |\n|---|---|---|---|---|---|"
    );
    for c in &t.copy {
        let _ = writeln!(
            s,
            "| {} | {} | {} | {:.3} | {:.3} | {:.0} % |",
            c.vertices,
            c.mode,
            c.bytes_per_vertex,
            c.mode_ms,
            c.copy_ms,
            100.0 * c.fraction_of_copy
        );
    }
}

/// The report's orientation-methods section.
fn orientation_section(s: &mut String, t: &Tradeoff) {
    use std::fmt::Write;
    let _ = writeln!(s, "\n## Orientation methods (smallest lung)\n");
    let _ = writeln!(
        s,
        "The true force for an orientation is Table 6.1's weights rotated with gravity (EQUATIONS.md \
         §3.3); each method's weights are fed to the same exact operator, so the error is the \
         method's alone. Sweeps of 15°: roll about the long axis (−180…180°, through both sides to \
         prone) and pitch about the left–right axis (−90…90°, head-down to sitting up).\n"
    );
    let _ = writeln!(
        s,
        "| method | sweep | RMS mm | max mm | RMS % |\n|---|---|---|---|---|"
    );
    for o in &t.orientation {
        let _ = writeln!(
            s,
            "| {} | {} | {:.3} | {:.3} | {:.2} |",
            o.method, o.sweep, o.error.rms_mm, o.error.max_mm, o.error.rms_percent
        );
    }
}

/// The report's stereo section (none without stereo timings).
fn stereo_section(s: &mut String, t: &Tradeoff) {
    use std::fmt::Write;
    if !t.stereo.is_empty() {
        let _ = writeln!(
            s,
            "\n## Stereo\n\nOne deformation pass per frame, then each eye draws the result (basis mode, \
             GPU time per frame by timestamp queries). The seed got 75/148 = 0.51 point-based and \
             23/46 = 0.50 polygon-based, because it deformed in the vertex shader, once per eye. The \
             second eye's cost is the draw alone (compare the last two time columns: a second \
             deformation would add the pass's time as well); where the draw is cheap against the \
             deformation, the ratio approaches 1. A software rasteriser's draw is not cheap at any \
             size: its vertex stage runs on the CPU, so even 32×24 pixels per eye cost a whole \
             vertex pass.\n"
        );
        let _ = writeln!(
            s,
            "| vertices | per eye | mono ms | stereo ms | deformation pass ms | one eye's draw (mono − deformation) ms | second eye (stereo − mono) ms | stereo/mono frame rate |\n|---|---|---|---|---|---|---|---|"
        );
        for st in &t.stereo {
            let _ = writeln!(
                s,
                "| {} | {}×{} | {:.3} | {:.3} | {:.3} | {:.3} | {:.3} | **{:.2}** |",
                st.vertices,
                st.eye.0,
                st.eye.1,
                st.mono_ms,
                st.stereo_ms,
                st.deform_ms,
                st.mono_ms - st.deform_ms,
                st.stereo_ms - st.mono_ms,
                st.rate_ratio
            );
        }
    }
}

/// The report's comparison with the seed's figures.
fn seed_section(s: &mut String, t: &Tradeoff) {
    use std::fmt::Write;
    let _ = writeln!(
        s,
        "\n## Beside the seed's figures\n\n\
         | figure | seed (ch. 7) | lungdyn (this run) |\n|---|---|---|\n\
         | 16 coefficients, RMS error vs eq. 7.1 | < 1 % (< 1 mm), α = 1.03 | {} |\n\
         | exact alternative | — | basis mode, max {} mm (round-off) |\n\
         | eq. 7.7 frame rate, mono / stereo | 148 / 75 FPS point-based, 46 / 23 polygon-based (GeForce FX 5600) | see the GPU column and the stereo section |\n\
         | per-node work, eq. 7.1 vs eq. 7.7 | 192 vs 16 MACs | {} |\n",
        t.rows
            .iter()
            .filter(|r| r.bands == Some(4))
            .map(|r| format!(
                "{} vertices: {:.2} % ({:.3} mm), α = {:.3}",
                r.vertices,
                r.error.rms_percent,
                r.error.rms_mm,
                r.alpha.unwrap_or(f64::NAN)
            ))
            .collect::<Vec<_>>()
            .join("; "),
        t.rows
            .iter()
            .filter(|r| r.mode == "basis")
            .map(|r| format!("{:.1e}", r.error.max_mm))
            .collect::<Vec<_>>()
            .join(" / "),
        t.rows
            .iter()
            .filter(|r| r.mode.starts_with("direct"))
            .map(|r| format!(
                "{} vertices: {:.0} values/node for eq. 7.1, 16 (16-bit) + 3 for eq. 7.7, 4 + 3 for the basis",
                r.vertices, r.floats_per_vertex
            ))
            .collect::<Vec<_>>()
            .join("; ")
    );
}

fn csv(t: &Tradeoff) -> String {
    let mut s = String::from(
        "vertices,mode,bands,coefficients,rms_mm,max_mm,rms_percent,max_percent,cpu_ms,cpu_threads,gpu_ms,mode_bake_s,transfer_bake_s,kernel_mib,alpha,cpu_speedup_vs_direct,quantisation_max_mm\n",
    );
    for r in &t.rows {
        s.push_str(&format!(
            "{},{},{},{},{:.6},{:.6},{:.4},{:.4},{:.4},{},{},{:.3},{:.3},{:.2},{},{},{}\n",
            r.vertices,
            r.mode,
            r.bands.map(|b| b.to_string()).unwrap_or_default(),
            r.bands.map(|b| (b * b).to_string()).unwrap_or_default(),
            r.error.rms_mm,
            r.error.max_mm,
            r.error.rms_percent,
            r.error.max_percent,
            r.cpu_ms,
            t.cpu_threads,
            r.gpu_ms.map(|g| format!("{g:.4}")).unwrap_or_default(),
            r.mode_bake_s,
            r.transfer_bake_s,
            r.kernel_mib,
            r.alpha.map(|a| format!("{a:.5}")).unwrap_or_default(),
            r.cpu_speedup_vs_direct
                .map(|x| format!("{x:.2}"))
                .unwrap_or_default(),
            r.quantisation_max_mm
                .map(|x| format!("{x:.6}"))
                .unwrap_or_default()
        ));
    }
    s
}

fn write_outputs(out: &Path, t: &Tradeoff) -> anyhow::Result<Vec<String>> {
    use crate::plot::{Panel, Series};
    use plotters::style::RGBColor;
    let palette = [
        RGBColor(31, 119, 180),
        RGBColor(230, 110, 20),
        RGBColor(44, 160, 44),
        RGBColor(214, 39, 40),
        RGBColor(148, 103, 189),
    ];
    let sizes: Vec<usize> = {
        let mut v: Vec<usize> = t.rows.iter().map(|r| r.vertices).collect();
        v.dedup();
        v
    };
    let sh = |v: usize| {
        t.rows
            .iter()
            .filter(move |r| r.vertices == v && r.bands.is_some())
    };
    let mut error_panel = Panel {
        title: "SH error against eq. 7.1".into(),
        x_label: "bands (n² coefficients)".into(),
        y_label: "RMS displacement error, % of max".into(),
        series: Vec::new(),
    };
    let mut time_panel = Panel {
        title: format!("CPU time per frame ({} threads)", t.cpu_threads),
        x_label: "bands".into(),
        y_label: "ms".into(),
        series: Vec::new(),
    };
    let max_bands = t.rows.iter().filter_map(|r| r.bands).max().unwrap_or(1) as f64;
    for (i, &v) in sizes.iter().enumerate() {
        let color = palette[i % palette.len()];
        error_panel.series.push(Series {
            label: format!("sh, {v} vertices"),
            points: sh(v)
                .map(|r| (r.bands.unwrap_or(0) as f64, r.error.rms_percent))
                .collect(),
            color,
            markers: false,
        });
        time_panel.series.push(Series {
            label: format!("sh, {v}"),
            points: sh(v)
                .map(|r| (r.bands.unwrap_or(0) as f64, r.cpu_ms))
                .collect(),
            color,
            markers: false,
        });
    }
    if let Some(&largest) = sizes.last() {
        for (mode, color) in [
            ("basis", RGBColor(0, 0, 0)),
            ("direct (eq. 7.1)", RGBColor(140, 86, 75)),
        ] {
            if let Some(r) = t
                .rows
                .iter()
                .find(|r| r.vertices == largest && r.mode == mode)
            {
                time_panel.series.push(Series {
                    label: format!("{mode}, {largest}"),
                    points: vec![(1.0, r.cpu_ms), (max_bands, r.cpu_ms)],
                    color,
                    markers: false,
                });
            }
        }
    }
    error_panel.series.push(Series {
        label: "seed's claim (< 1 %)".into(),
        points: vec![(1.0, 1.0), (max_bands, 1.0)],
        color: RGBColor(120, 120, 120),
        markers: false,
    });
    let mut orient_panel = Panel {
        title: "Orientation methods (roll sweep)".into(),
        x_label: "roll about the long axis, degrees".into(),
        y_label: "RMS displacement error, mm".into(),
        series: Vec::new(),
    };
    for (i, o) in t
        .orientation
        .iter()
        .filter(|o| o.sweep == "roll")
        .enumerate()
    {
        orient_panel.series.push(Series {
            label: o.method.clone(),
            points: o.series.clone(),
            color: palette[i % palette.len()],
            markers: true,
        });
    }
    let stem = out
        .file_name()
        .and_then(|s| s.to_str())
        .context("--out needs a file name")?
        .to_string();
    let png = out.with_file_name(format!("{stem}.png"));
    let (png, svg) = crate::plot::write(&png, &[error_panel, time_panel, orient_panel])?;
    let md = out.with_file_name(format!("{stem}.md"));
    let csv_path = out.with_file_name(format!("{stem}.csv"));
    for (path, text) in [(&md, markdown(t, &stem)), (&csv_path, csv(t))] {
        outfile::write_atomically(path, |w| {
            use std::io::Write;
            w.write_all(text.as_bytes())
        })?;
    }
    Ok([md, csv_path, png, svg]
        .iter()
        .map(|p| p.display().to_string())
        .collect())
}

/// A short summary for the terminal.
pub fn text(t: &Tradeoff) -> String {
    let mut s = String::new();
    for r in &t.rows {
        s.push_str(&format!(
            "{:>8} {:<18} {:>4} RMS {:>8.3} mm ({:>6.2} %) max {:>8.3} mm  CPU {:>8.3} ms{}  GPU {:>8} ms\n",
            r.vertices,
            r.mode,
            r.bands.map(|b| b.to_string()).unwrap_or_default(),
            r.error.rms_mm,
            r.error.rms_percent,
            r.error.max_mm,
            r.cpu_ms,
            r.cpu_speedup_vs_direct
                .map(|x| format!(" ({x:.1}x eq. 7.1)"))
                .unwrap_or_default(),
            fmt_opt(r.gpu_ms, 3)
        ));
    }
    for c in &t.copy {
        s.push_str(&format!(
            "{:>8} {:<18} {:.3} ms vs copy {:.3} ms: {:.0} % of copy bandwidth\n",
            c.vertices,
            c.mode,
            c.mode_ms,
            c.copy_ms,
            100.0 * c.fraction_of_copy
        ));
    }
    for st in &t.stereo {
        s.push_str(&format!(
            "{:>8} {}×{} per eye: stereo/mono frame rate {:.2} (mono {:.3} ms, stereo {:.3} ms, deformation {:.3} ms)\n",
            st.vertices, st.eye.0, st.eye.1, st.rate_ratio, st.mono_ms, st.stereo_ms, st.deform_ms
        ));
    }
    s.push_str(&format!("wrote {}\n", t.files.join(", ")));
    s
}
