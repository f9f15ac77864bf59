//! Ridge regression in closed form, from accumulated second moments.
//!
//! Targets t (m values) are fitted from features x (d values) with an intercept:
//! t ≈ M x + c. With centred moments Sxx = Cov(x, x), Stx = Cov(t, x), the solution is
//! M = Stx (Sxx + λI)^-1 and c = mean(t) - M mean(x), solved by Cholesky in f64.

/// Running sums over samples: enough for means and covariances.
pub struct Moments {
    pub d: usize,
    pub m: usize,
    pub n: f64,
    sx: Vec<f64>,
    st: Vec<f64>,
    sxx: Vec<f64>,
    stx: Vec<f64>,
}

impl Moments {
    pub fn new(d: usize, m: usize) -> Moments {
        Moments { d, m, n: 0.0, sx: vec![0.0; d], st: vec![0.0; m], sxx: vec![0.0; d * d], stx: vec![0.0; m * d] }
    }

    /// Adds samples given as channel-major planes: `x[j * len + p]`, `t[i * len + p]`.
    /// Positions are taken every `stride`-th (a bounded, even subsample of large maps).
    pub fn add_planes(&mut self, x: &[f32], t: &[f32], len: usize, stride: usize) {
        let (d, m) = (self.d, self.m);
        let picks: Vec<usize> = (0..len).step_by(stride.max(1)).collect();
        let xs: Vec<Vec<f64>> = (0..d).map(|j| picks.iter().map(|&p| x[j * len + p] as f64).collect()).collect();
        let ts: Vec<Vec<f64>> = (0..m).map(|i| picks.iter().map(|&p| t[i * len + p] as f64).collect()).collect();
        self.add_columns(&xs, &ts);
    }

    /// Adds samples given column by column: `xs[j][s]` is feature j of sample s.
    pub fn add_columns(&mut self, xs: &[Vec<f64>], ts: &[Vec<f64>]) {
        let (d, m) = (self.d, self.m);
        let count = xs.first().or(ts.first()).map_or(0, Vec::len);
        let dot = |a: &[f64], b: &[f64]| a.iter().zip(b).map(|(p, q)| p * q).sum::<f64>();
        use rayon::prelude::*;
        let sxx: Vec<f64> = (0..d * d).into_par_iter().map(|k| if k / d <= k % d { dot(&xs[k / d], &xs[k % d]) } else { 0.0 }).collect();
        let stx: Vec<f64> = (0..m * d).into_par_iter().map(|k| dot(&ts[k / d], &xs[k % d])).collect();
        for a in 0..d {
            for b in a..d {
                self.sxx[a * d + b] += sxx[a * d + b];
            }
            self.sx[a] += xs[a].iter().sum::<f64>();
        }
        for (acc, v) in self.stx.iter_mut().zip(stx) {
            *acc += v;
        }
        for i in 0..m {
            self.st[i] += ts[i].iter().sum::<f64>();
        }
        self.n += count as f64;
    }

    /// (M as m x d row-major, c), with ridge `lambda` relative to the mean feature variance,
    /// pulling M towards `prior` (m x d) where given, towards 0 otherwise.
    /// None when there are no samples or the system is not positive definite.
    pub fn solve(&self, lambda: f64, prior: Option<&[f64]>) -> Option<(Vec<f64>, Vec<f64>)> {
        let (d, m, n) = (self.d, self.m, self.n);
        if n < 2.0 {
            return None;
        }
        let mx: Vec<f64> = self.sx.iter().map(|s| s / n).collect();
        let mt: Vec<f64> = self.st.iter().map(|s| s / n).collect();
        let mut a = vec![0.0; d * d];
        for i in 0..d {
            for j in i..d {
                let v = self.sxx[i * d + j] / n - mx[i] * mx[j];
                a[i * d + j] = v;
                a[j * d + i] = v;
            }
        }
        let mean_var = (0..d).map(|i| a[i * d + i]).sum::<f64>() / d.max(1) as f64;
        // A dead channel (zero variance everywhere) still gets a well-posed system.
        let ridge = lambda * mean_var.max(1e-12);
        for i in 0..d {
            a[i * d + i] += ridge;
        }
        let l = cholesky(&a, d)?;
        let mut mm = vec![0.0; m * d];
        for i in 0..m {
            let rhs: Vec<f64> = (0..d).map(|j| self.stx[i * d + j] / n - mt[i] * mx[j] + prior.map_or(0.0, |p| ridge * p[i * d + j])).collect();
            let sol = cholesky_solve(&l, d, &rhs);
            mm[i * d..(i + 1) * d].copy_from_slice(&sol);
        }
        let c = (0..m).map(|i| mt[i] - (0..d).map(|j| mm[i * d + j] * mx[j]).sum::<f64>()).collect();
        mm.iter().all(|v| v.is_finite()).then_some((mm, c))
    }
}

/// Lower-triangular L with A = L Lᵀ, or None when A is not positive definite.
fn cholesky(a: &[f64], d: usize) -> Option<Vec<f64>> {
    let mut l = vec![0.0; d * d];
    for i in 0..d {
        for j in 0..=i {
            let s: f64 = a[i * d + j] - (0..j).map(|k| l[i * d + k] * l[j * d + k]).sum::<f64>();
            if i == j {
                if s <= 0.0 || !s.is_finite() {
                    return None;
                }
                l[i * d + i] = s.sqrt();
            } else {
                l[i * d + j] = s / l[j * d + j];
            }
        }
    }
    Some(l)
}

fn cholesky_solve(l: &[f64], d: usize, b: &[f64]) -> Vec<f64> {
    let mut y = vec![0.0; d];
    for i in 0..d {
        y[i] = (b[i] - (0..i).map(|k| l[i * d + k] * y[k]).sum::<f64>()) / l[i * d + i];
    }
    let mut x = vec![0.0; d];
    for i in (0..d).rev() {
        x[i] = (y[i] - (i + 1..d).map(|k| l[k * d + i] * x[k]).sum::<f64>()) / l[i * d + i];
    }
    x
}

#[cfg(test)]
mod tests {
    use super::Moments;

    #[test]
    fn recovers_an_exact_linear_map() {
        // t0 = 2 x0 - x1 + 3, t1 = 0.5 x1 - 1 on scattered samples.
        let len = 64;
        let x: Vec<f32> = (0..2 * len).map(|k| ((k * 37 % 101) as f32 / 10.0).sin() * 3.0).collect();
        let t: Vec<f32> = (0..len).map(|p| 2.0 * x[p] - x[len + p] + 3.0).chain((0..len).map(|p| 0.5 * x[len + p] - 1.0)).collect();
        let mut m = Moments::new(2, 2);
        m.add_planes(&x, &t, len, 1);
        let (mm, c) = m.solve(1e-9, None).unwrap();
        for (got, want) in mm.iter().zip([2.0, -1.0, 0.0, 0.5]).chain(c.iter().zip([3.0, -1.0])) {
            assert!((got - want).abs() < 1e-4, "{got} vs {want}");
        }
    }
}
