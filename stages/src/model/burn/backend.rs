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

use burn::tensor::Device;

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
    fn default_backend_is_available_and_named() {
        let b = Backend::default();
        assert!(Backend::available().contains(&b));
        assert_eq!(Backend::from_name(b.name()), Some(b));
    }
}
