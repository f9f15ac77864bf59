//! Optics: lens files, scalar-diffraction PSFs, the blur-index map, single-lens degradation,
//! synthetic thermal scenes.

pub mod blur_index;
pub mod conditions;
pub mod blur_map;
pub mod degrade;
pub mod fft2;
pub mod lens;
pub mod npy;
pub mod psf;
pub mod psf_set;
pub mod rng;
pub mod synth;
