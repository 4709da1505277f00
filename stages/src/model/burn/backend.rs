//! The one place where the burn backend of the radiance field is chosen.
//!
//! burn 0.22 has no backend type parameter: tensors are `Tensor<D>` and the backend is a runtime
//! [`Device`]. The cargo features of this crate decide which devices exist; [`Backend::default`]
//! picks one with this priority: `cuda`, `wgpu`, `ndarray`, `flex` (a GPU wins over the CPU; an
//! explicitly requested `ndarray` wins over the default `flex`). Several can be compiled in at
//! once, which the benchmark uses to compare flex and ndarray in one binary.
//!
//! Training wraps the device with autodiff ([`Backend::train_device`]); inference uses the plain
//! device ([`Backend::device`]).

use std::sync::OnceLock;

use burn::tensor::{Device, Tensor};

/// A burn backend this build can run the field on.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Backend {
    /// burn-flex: pure-Rust CPU backend (default; the successor of burn-ndarray).
    Flex,
    /// burn-ndarray: the deprecated CPU backend, kept for comparison.
    NdArray,
    /// wgpu: any GPU through Vulkan/Metal/DX12/WebGPU.
    Wgpu,
    /// CUDA: NVIDIA GPUs.
    Cuda,
}

impl Backend {
    /// The CPU backend every engine and every GPU backend is held to in tests (always compiled
    /// in: the crate's default feature).
    pub const REFERENCE: Backend = Backend::Flex;

    /// Every backend, compiled in or not.
    pub const ALL: [Backend; 4] = [
        Backend::Flex,
        Backend::NdArray,
        Backend::Wgpu,
        Backend::Cuda,
    ];

    /// The backends compiled into this build, in priority order.
    pub fn available() -> Vec<Backend> {
        let mut all = Vec::new();
        if cfg!(feature = "cuda") {
            all.push(Backend::Cuda);
        }
        if cfg!(feature = "wgpu") {
            all.push(Backend::Wgpu);
        }
        if cfg!(feature = "ndarray") {
            all.push(Backend::NdArray);
        }
        if cfg!(feature = "flex") {
            all.push(Backend::Flex);
        }
        all
    }

    /// Short lowercase name (`flex`, `ndarray`, `wgpu`, `cuda`).
    pub fn name(self) -> &'static str {
        match self {
            Backend::Flex => "flex",
            Backend::NdArray => "ndarray",
            Backend::Wgpu => "wgpu",
            Backend::Cuda => "cuda",
        }
    }

    /// Parses [`Backend::name`]; `None` for an unknown or not compiled-in backend.
    pub fn from_name(name: &str) -> Option<Backend> {
        Self::available().into_iter().find(|b| b.name() == name)
    }

    /// The plain (inference) device of this backend.
    ///
    /// # Panics
    /// If the backend is not compiled in (see [`Backend::available`]).
    #[allow(unreachable_code, unused_variables)]
    pub fn device(self) -> Device {
        match self {
            Backend::Flex => {
                #[cfg(feature = "flex")]
                return Device::flex();
            }
            Backend::NdArray => {
                #[cfg(feature = "ndarray")]
                #[allow(deprecated)] // kept on purpose, for comparison with flex
                return Device::ndarray();
            }
            Backend::Wgpu => {
                #[cfg(feature = "wgpu")]
                return Device::wgpu(Default::default());
            }
            Backend::Cuda => {
                #[cfg(feature = "cuda")]
                return Device::cuda(0);
            }
        }
        panic!(
            "backend `{}` is not compiled in; enable the cargo feature of the same name",
            self.name()
        )
    }

    /// The device with autodiff, for training.
    pub fn train_device(self) -> Device {
        self.device().autodiff()
    }

    /// Whether this backend has a device to run on here (checked once per process): the CPU
    /// backends always; a GPU backend needs its driver and a device (wgpu: a Vulkan, Metal or
    /// DX12 adapter, on a machine without a GPU e.g. Mesa's llvmpipe from Debian's
    /// `mesa-vulkan-drivers`; cuda: an NVIDIA GPU and driver). The error says what failed.
    pub fn check_device(self) -> Result<(), String> {
        static CHECKED: [OnceLock<Result<(), String>>; 4] = [
            OnceLock::new(),
            OnceLock::new(),
            OnceLock::new(),
            OnceLock::new(),
        ];
        match self {
            Backend::Flex | Backend::NdArray => Ok(()),
            Backend::Wgpu => CHECKED[2].get_or_init(|| probe(self)).clone(),
            Backend::Cuda => CHECKED[3].get_or_init(|| probe(self)).clone(),
        }
    }
}

/// Runs a sum on `b`'s device; a missing driver or device panics inside the runtime, which is
/// caught and named.
fn probe(b: Backend) -> Result<(), String> {
    if !Backend::available().contains(&b) {
        return Err(format!("`{}` is not compiled in", b.name()));
    }
    let run = std::panic::catch_unwind(|| {
        let t = Tensor::<1>::from_floats([1.0f32, 2.0].as_slice(), &b.device());
        t.sum()
            .into_data()
            .try_to_vec::<f32>()
            .map_err(|e| format!("{e:?}"))
    });
    match run {
        Ok(Ok(v)) if v == [3.0] => Ok(()),
        Ok(Ok(v)) => Err(format!("a test sum on `{}` gave {v:?}", b.name())),
        Ok(Err(e)) => Err(e),
        Err(panic) => Err(panic
            .downcast_ref::<String>()
            .cloned()
            .or_else(|| panic.downcast_ref::<&str>().map(|s| s.to_string()))
            .unwrap_or_else(|| "the runtime panicked".into())),
    }
}

impl Default for Backend {
    /// The highest-priority compiled-in backend; `Flex` when none is (then [`Backend::device`]
    /// panics with a message naming the missing feature).
    fn default() -> Self {
        Self::available().first().copied().unwrap_or(Backend::Flex)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn cpu_backends_always_have_a_device_and_missing_ones_are_named() {
        assert_eq!(Backend::REFERENCE.check_device(), Ok(()));
        for b in [Backend::Wgpu, Backend::Cuda] {
            if !Backend::available().contains(&b) {
                let e = b.check_device().unwrap_err();
                assert!(e.contains("not compiled in"), "{e}");
            }
        }
    }

    #[test]
    fn default_backend_is_available_and_named() {
        let b = Backend::default();
        assert!(Backend::available().contains(&b));
        assert_eq!(Backend::from_name(b.name()), Some(b));
    }
}
