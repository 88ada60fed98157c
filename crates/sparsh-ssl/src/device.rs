//! Where a run computes: burn's CPU backend (`flex`), a GPU through wgpu (Vulkan, Metal or DX12;
//! Mesa's lavapipe is a software one on the CPU), or an NVIDIA GPU through CUDA (the `cuda`
//! feature). Every model is drawn on the CPU under its seed and then moved, so a recipe and seed
//! start from the same weights on every device.

use std::fmt;
use std::str::FromStr;

use burn::module::{Module, ModuleVisitor, Param};
use burn::prelude::{Device, Tensor};
use burn::tensor::DeviceType;

use crate::Error;

/// The kind of device a run asks for (`--device`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum DeviceKind {
    /// burn's CPU backend on the rayon pool (the default).
    #[default]
    Cpu,
    /// A GPU (or a software rasteriser) through wgpu.
    Wgpu,
    /// An NVIDIA GPU through CUDA; needs a build with the `cuda` feature.
    Cuda,
    /// CUDA when this build has it and the machine a CUDA GPU, else a hardware wgpu adapter
    /// (software rasterisers are skipped: on the same cores the CPU backend is faster), else the
    /// CPU.
    Auto,
}

impl FromStr for DeviceKind {
    type Err = String;

    fn from_str(s: &str) -> Result<Self, Self::Err> {
        match s {
            "cpu" => Ok(DeviceKind::Cpu),
            "wgpu" => Ok(DeviceKind::Wgpu),
            "cuda" => Ok(DeviceKind::Cuda),
            "auto" => Ok(DeviceKind::Auto),
            other => Err(format!(
                "unknown device '{other}': expected cpu, wgpu, cuda or auto"
            )),
        }
    }
}

impl fmt::Display for DeviceKind {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(match self {
            DeviceKind::Cpu => "cpu",
            DeviceKind::Wgpu => "wgpu",
            DeviceKind::Cuda => "cuda",
            DeviceKind::Auto => "auto",
        })
    }
}

/// The devices of one process: the batch of every step is split across them (data-parallel),
/// the first holds the parameters and the optimizer state.
#[derive(Debug, Clone)]
pub struct Devices {
    /// The kind they were chosen as (`Auto` resolved).
    pub kind: DeviceKind,
    /// The devices, without autodiff.
    pub devices: Vec<Device>,
    /// One name per device, for logs.
    pub names: Vec<String>,
}

impl Devices {
    /// The CPU backend, one device.
    pub fn cpu() -> Self {
        Devices {
            kind: DeviceKind::Cpu,
            devices: vec![Device::flex()],
            names: vec!["cpu".into()],
        }
    }

    /// The devices `kind` names; `indices` picks several of that kind by their position in
    /// [`list`] (empty: the kind's default device). On the CPU every index is the same backend:
    /// several CPU "devices" split each batch like micro-batches on the shared cores (a way to
    /// test data-parallel training without GPUs, not a speed-up).
    pub fn choose(kind: DeviceKind, indices: &[usize]) -> Result<Self, Error> {
        let kind = match kind {
            DeviceKind::Auto => auto_kind(),
            k => k,
        };
        if let Some(dup) = indices
            .iter()
            .enumerate()
            .find(|(i, d)| indices[..*i].contains(d))
            .map(|(_, d)| d)
            && kind != DeviceKind::Cpu
        {
            return Err(Error::Config(format!(
                "--devices names {kind} device {dup} twice"
            )));
        }
        if kind == DeviceKind::Cpu {
            let n = indices.len().max(1);
            return Ok(Devices {
                kind,
                devices: vec![Device::flex(); n],
                names: (0..n).map(|i| format!("cpu:{i}")).collect(),
            });
        }
        let available = list(kind)?;
        if available.is_empty() {
            return Err(Error::Config(match kind {
                DeviceKind::Wgpu => "--device wgpu: no wgpu adapter on this machine (no GPU \
                                     driver; on Linux `apt install mesa-vulkan-drivers` gives a \
                                     software one)"
                    .into(),
                _ => format!("--device {kind}: no such device on this machine"),
            }));
        }
        let picked: Vec<usize> = if indices.is_empty() {
            vec![0]
        } else {
            indices.to_vec()
        };
        let mut devices = Vec::new();
        let mut names = Vec::new();
        for i in picked {
            let (device, name) = available.get(i).cloned().ok_or_else(|| {
                Error::Config(format!(
                    "--devices: {kind} device {i} does not exist; this machine has {} ({})",
                    available.len(),
                    available
                        .iter()
                        .enumerate()
                        .map(|(k, (_, n))| format!("{k}: {n}"))
                        .collect::<Vec<_>>()
                        .join(", ")
                ))
            })?;
            devices.push(device);
            names.push(format!("{kind}:{i} {name}"));
        }
        Ok(Devices {
            kind,
            devices,
            names,
        })
    }

    /// The device holding the parameters.
    pub fn main(&self) -> &Device {
        &self.devices[0]
    }
}

/// The devices of `kind` this build and machine have, in burn's enumeration order, with their
/// names (`--devices` indexes this list). The CPU is one device.
pub fn list(kind: DeviceKind) -> Result<Vec<(Device, String)>, Error> {
    let named = |d: Device| {
        let name = d
            .identity()
            .map_or_else(|| "unnamed".to_string(), |id| id.name);
        (d, name)
    };
    match kind {
        DeviceKind::Cpu => Ok(vec![(Device::flex(), "cpu".into())]),
        DeviceKind::Wgpu => Ok(Device::enumerate(DeviceType::Wgpu)
            .into_iter()
            .map(named)
            .collect()),
        DeviceKind::Cuda => cuda_devices().map(|v| v.into_iter().map(named).collect()),
        DeviceKind::Auto => list(auto_kind()),
    }
}

#[cfg(feature = "cuda")]
fn cuda_devices() -> Result<Vec<Device>, Error> {
    Ok(Device::enumerate(DeviceType::Cuda).into_vec())
}

#[cfg(not(feature = "cuda"))]
fn cuda_devices() -> Result<Vec<Device>, Error> {
    Err(Error::Config(
        "--device cuda: this build has no CUDA; rebuild with `--features cuda`".into(),
    ))
}

/// What `auto` resolves to on this machine.
fn auto_kind() -> DeviceKind {
    if cuda_devices().is_ok_and(|d| !d.is_empty()) {
        return DeviceKind::Cuda;
    }
    let hardware = Device::enumerate(DeviceType::Wgpu)
        .into_iter()
        .any(|d| d.identity().is_some_and(|id| id.physical.is_some()));
    if hardware {
        DeviceKind::Wgpu
    } else {
        DeviceKind::Cpu
    }
}

/// Parses `--devices 0,1,2`.
pub fn parse_indices(s: &str) -> Result<Vec<usize>, String> {
    s.split(',')
        .map(|p| {
            p.trim()
                .parse::<usize>()
                .map_err(|_| format!("--devices: '{p}' is not a device index (e.g. 0,1)"))
        })
        .collect()
}

/// The device `module` computes on (the CPU for a module without parameters).
pub fn device_of<M: Module>(module: &M) -> Device {
    module
        .devices()
        .first()
        .cloned()
        .unwrap_or_else(Device::flex)
}

/// `module` on `device`: returned as it is when it lives there already (so a CPU run computes
/// exactly as it always did), else forked there. Models are drawn on the CPU under their seed
/// and moved with this, so a seed starts from the same weights on every device. Pass an
/// autodiff device (`device.clone().autodiff()`) for a module that is to be trained.
pub fn on_device<M: Module>(module: M, device: &Device) -> M {
    if module.devices().iter().all(|d| d == device) {
        module
    } else {
        module.fork(device)
    }
}

static INIT_LOCK: std::sync::Mutex<()> = std::sync::Mutex::new(());

/// Runs `f` (a model initialization) with burn's random generator seeded by `seed`, holding a
/// process-wide lock: burn's generator is global, so initializations running at the same time
/// on other threads would otherwise interleave their draws and break determinism.
pub fn seeded<T>(device: &Device, seed: u64, f: impl FnOnce() -> T) -> T {
    let _guard = INIT_LOCK.lock().unwrap_or_else(|e| e.into_inner());
    device.seed(seed);
    f()
}

/// A tensor drawn from `distribution` under `seed` ([`seeded`]). Tests draw their inputs this
/// way: a draw outside the lock takes numbers from burn's global generator while a seeded
/// initialization on another thread is drawing, and that initialization changes.
#[cfg(test)]
pub(crate) fn seeded_random<const D: usize>(
    device: &Device,
    seed: u64,
    shape: [usize; D],
    distribution: burn::tensor::Distribution,
) -> Tensor<D> {
    seeded(device, seed, || Tensor::random(shape, distribution, device))
}

/// Draws every parameter of `module` that is still uninitialized: burn initializes parameters
/// lazily, on first use, so without this the draws happen wherever the module is first used
/// (another thread, after another seeding) instead of under [`seeded`].
pub fn draw_parameters<M: Module>(module: &M) {
    struct Draw;
    impl ModuleVisitor for Draw {
        fn visit_float<const D: usize>(&mut self, param: &Param<Tensor<D>>) {
            let _ = param.val();
        }
    }
    module.visit(&mut Draw);
}

/// [`seeded`] for a module initialization, with every parameter drawn under the seed.
pub fn seeded_module<M: Module>(device: &Device, seed: u64, f: impl FnOnce() -> M) -> M {
    seeded(device, seed, || {
        let module = f();
        draw_parameters(&module);
        module
    })
}
