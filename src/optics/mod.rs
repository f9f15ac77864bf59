//! Optics: the camera's PSF prior as the compiler consumes it.

pub mod blur_map;
pub mod npy;
