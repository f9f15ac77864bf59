//! Scales and zero points: asymmetric per-tensor activations, symmetric per-channel weights,
//! int32 biases at scale s_in * s_w.

/// Activation storage type: `u8` for ONNX Runtime on x86 (its u8s8 kernels), `i8` for RKNN.
#[derive(Clone, Copy, Debug, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum ActivationType {
    U8,
    I8,
}

impl ActivationType {
    pub fn bounds(self) -> (i32, i32) {
        match self {
            ActivationType::U8 => (0, 255),
            ActivationType::I8 => (-128, 127),
        }
    }
}

/// The scale given to a range too small to quantize (an all-zero activation): any finite
/// positive scale represents zero exactly; 1/255 keeps the integer model's numbers ordinary.
pub const DEGENERATE_SCALE: f64 = 1.0 / 255.0;
/// Ranges narrower than this (relative to their magnitude, or absolutely) count as degenerate:
/// a scale near f32's smallest normals would overflow x / scale and the int32 bias.
const MIN_RANGE: f64 = 1e-30;

/// Whether [lo, hi] is too narrow (or not finite) to derive a scale from.
pub fn degenerate_range(lo: f64, hi: f64) -> bool {
    !(hi - lo).is_finite() || hi - lo < MIN_RANGE
}

#[derive(Clone, Copy, Debug, PartialEq)]
pub struct QParams {
    pub scale: f64,
    pub zero_point: i32,
    pub qmin: i32,
    pub qmax: i32,
}

impl QParams {
    /// Asymmetric parameters covering [lo, hi] (lo <= 0 <= hi), zero exactly representable.
    pub fn activation(lo: f64, hi: f64, ty: ActivationType) -> QParams {
        let (qmin, qmax) = ty.bounds();
        let (lo, hi) = (lo.min(0.0), hi.max(0.0));
        if degenerate_range(lo, hi) {
            return QParams { scale: DEGENERATE_SCALE, zero_point: 0.clamp(qmin, qmax), qmin, qmax };
        }
        let scale = (hi - lo) / (qmax - qmin) as f64;
        let zero_point = (qmin as f64 - lo / scale).round().clamp(qmin as f64, qmax as f64) as i32;
        QParams { scale, zero_point, qmin, qmax }
    }

    /// Parameters covering every value of a constant (a gate map, an added constant).
    pub fn covering(values: &[f32], ty: ActivationType) -> QParams {
        let (lo, hi) = values.iter().fold((0.0f64, 0.0f64), |(a, b), &x| (a.min(x as f64), b.max(x as f64)));
        QParams::activation(lo, hi, ty)
    }

    pub fn quantize(&self, x: f64) -> i32 {
        ((x / self.scale).round() as i64 + self.zero_point as i64).clamp(self.qmin as i64, self.qmax as i64) as i32
    }

    pub fn fake_quant(&self, x: f64) -> f64 {
        (self.quantize(x) - self.zero_point) as f64 * self.scale
    }
}

/// Symmetric per-output-channel int8 weights: `bits` 8 gives [-127, 127]; 7 gives [-63, 63]
/// (ONNX Runtime's `reduce_range`, which avoids the int16 saturation of u8s8 products on
/// AVX2 without VNNI).
#[derive(Clone, Debug)]
pub struct QuantizedWeights {
    pub values: Vec<i8>,
    pub scales: Vec<f64>,
}

pub fn quantize_weights(w: &[f32], out_channels: usize, bits: u32) -> QuantizedWeights {
    let qmax = ((1i32 << (bits - 1)) - 1) as f64;
    let per = w.len() / out_channels.max(1);
    let mut values = Vec::with_capacity(w.len());
    let mut scales = Vec::with_capacity(out_channels);
    for c in w.chunks(per.max(1)) {
        let peak = c.iter().filter(|v| v.is_finite()).fold(0.0f64, |m, &v| m.max((v as f64).abs()));
        let s = if peak > MIN_RANGE { peak / qmax } else { 1.0 };
        scales.push(s);
        values.extend(c.iter().map(|&v| ((v as f64) / s).round().clamp(-qmax, qmax) as i8));
    }
    QuantizedWeights { values, scales }
}

/// int32 bias at scale s_in * s_w[c]; returns the values and how many had to be clamped.
pub fn quantize_bias(b: &[f32], input_scale: f64, weight_scales: &[f64]) -> (Vec<i32>, Vec<f64>, usize) {
    let mut clamped = 0;
    let scales: Vec<f64> = weight_scales.iter().map(|s| s * input_scale).collect();
    let values = b
        .iter()
        .zip(&scales)
        .map(|(&v, &s)| {
            let q = (v as f64 / s).round();
            if q.abs() > i32::MAX as f64 {
                clamped += 1;
            }
            q.clamp(i32::MIN as f64 + 1.0, i32::MAX as f64) as i32
        })
        .collect();
    (values, scales, clamped)
}

/// Mean output shift per output channel that weight rounding causes: sum over each filter of
/// (W_q - W) * E[x] for its input channel (data-free bias correction, Nagel et al. 2019; the
/// zero padding at the borders is ignored). `shape` is [O, I/group, kh, kw].
pub fn weight_rounding_shift(w: &[f32], shape: &[usize], group: usize, q: &QuantizedWeights, input_means: &[f64]) -> Vec<f64> {
    let (out, per_group_in) = (shape[0], shape.get(1).copied().unwrap_or(1));
    let taps: usize = shape.iter().skip(2).product::<usize>().max(1);
    let out_per_group = (out / group.max(1)).max(1);
    (0..out)
        .map(|o| {
            let s = q.scales[o];
            let first_input = (o / out_per_group) * per_group_in;
            (0..per_group_in)
                .map(|i| {
                    let mean = input_means.get(first_input + i).copied().unwrap_or(0.0);
                    let base = (o * per_group_in + i) * taps;
                    (base..base + taps).map(|k| q.values[k] as f64 * s - w[k] as f64).sum::<f64>() * mean
                })
                .sum()
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn zero_is_exact_and_degenerate_ranges_are_finite() {
        let p = QParams::activation(-0.3, 5.0, ActivationType::U8);
        assert_eq!(p.fake_quant(0.0), 0.0);
        assert!((p.fake_quant(5.0) - 5.0).abs() <= p.scale);
        let z = QParams::activation(0.0, 0.0, ActivationType::U8);
        assert!(z.scale.is_finite() && z.scale > 0.0 && degenerate_range(0.0, 0.0));
        assert!(!degenerate_range(0.0, 1.0));
        assert_eq!(z.fake_quant(0.0), 0.0);
    }

    #[test]
    fn weights_per_channel() {
        let q = quantize_weights(&[1.0, -0.5, 0.0, 0.0, 0.02, 0.01], 3, 8);
        assert_eq!(q.values, vec![127, -64, 0, 0, 127, 64]);
        assert_eq!(q.scales[1], 1.0, "an all-zero channel gets a finite scale");
    }
}
