//! Ridge regression in closed form, from accumulated second moments.
//!
//! Targets t (m values) are fitted from features x (d values) with an intercept:
//! t ≈ M x + c. With centred moments Sxx = Cov(x, x), Stx = Cov(t, x), the solution is
//! M = Stx (Sxx + λI)^-1 and c = mean(t) - M mean(x), solved by Cholesky in f64.

/// Running sums over samples: enough for means and covariances.
#[derive(Clone)]
pub struct Moments {
    pub d: usize,
    pub m: usize,
    pub n: f64,
    sx: Vec<f64>,
    st: Vec<f64>,
    /// Σ t² per target (for residuals).
    stt: Vec<f64>,
    sxx: Vec<f64>,
    stx: Vec<f64>,
}

impl Moments {
    pub fn new(d: usize, m: usize) -> Moments {
        Moments { d, m, n: 0.0, sx: vec![0.0; d], st: vec![0.0; m], stt: vec![0.0; m], sxx: vec![0.0; d * d], stx: vec![0.0; m * d] }
    }

    /// Adds samples given as channel-major planes: `x[j * len + p]`, `t[i * len + p]`, at
    /// positions `picks` (a bounded subsample of large maps, see [`spread_positions`]).
    pub fn add_planes(&mut self, x: &[f32], t: &[f32], len: usize, picks: &[usize]) {
        let (d, m) = (self.d, self.m);
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
            self.stt[i] += ts[i].iter().map(|v| v * v).sum::<f64>();
        }
        self.n += count as f64;
    }

    /// Adds another set of samples of the same features and targets.
    pub fn merge(&mut self, o: &Moments) {
        for (a, b) in [(&mut self.sx, &o.sx), (&mut self.st, &o.st), (&mut self.stt, &o.stt), (&mut self.sxx, &o.sxx), (&mut self.stx, &o.stx)] {
            a.iter_mut().zip(b).for_each(|(p, q)| *p += q);
        }
        self.n += o.n;
    }

    /// Σ over samples and targets of (t − M x − c)², from the sums alone.
    pub fn residual(&self, mm: &[f64], c: &[f64]) -> f64 {
        let d = self.d;
        let sxx = |a: usize, b: usize| if a <= b { self.sxx[a * d + b] } else { self.sxx[b * d + a] };
        (0..self.m)
            .map(|i| {
                let w = &mm[i * d..(i + 1) * d];
                let wtx: f64 = (0..d).map(|j| w[j] * self.stx[i * d + j]).sum();
                let wsx: f64 = (0..d).map(|j| w[j] * self.sx[j]).sum();
                let quad: f64 = (0..d).map(|a| w[a] * (0..d).map(|b| sxx(a, b) * w[b]).sum::<f64>()).sum();
                self.stt[i] - 2.0 * wtx - 2.0 * c[i] * self.st[i] + quad + 2.0 * c[i] * wsx + self.n * c[i] * c[i]
            })
            .sum()
    }

    /// `prior` kept as it is, with the intercept that matches the targets' means.
    pub fn intercept_only(&self, prior: &[f64]) -> (Vec<f64>, Vec<f64>) {
        let n = self.n.max(1.0);
        let c = (0..self.m).map(|i| (self.st[i] - (0..self.d).map(|j| prior[i * self.d + j] * self.sx[j]).sum::<f64>()) / n).collect();
        (prior.to_vec(), c)
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

/// About `count` of the positions `0..total`, one drawn at random from each of `count` equal
/// strata (all of them when `count >= total`). Not every k-th: a regular stride that divides
/// a map's width samples the same columns on every row, and behind a 2x nearest upsampling
/// even and odd columns see different neighbourhoods, so a fit on one half is wrong on the
/// other.
pub fn spread_positions(total: usize, count: usize, seed: u64) -> Vec<usize> {
    if count >= total {
        return (0..total).collect();
    }
    let mut rng = crate::optics::rng::Rng::new(seed);
    let step = total as f64 / count.max(1) as f64;
    (0..count).map(|k| ((k as f64 + rng.uniform()) * step).floor() as usize).map(|p| p.min(total - 1)).collect()
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
    use super::{spread_positions, Moments};

    #[test]
    fn spread_positions_cover_odd_and_even_columns() {
        // 64 columns, a quarter of the positions: a stride of 4 would see columns 0, 4, 8, …
        let p = spread_positions(64 * 48, 64 * 12, 7);
        assert_eq!(p.len(), 64 * 12);
        assert!(p.windows(2).all(|w| w[0] < w[1]), "sorted, distinct");
        let odd = p.iter().filter(|&&q| q % 64 % 2 == 1).count();
        assert!(odd > p.len() / 3 && odd < 2 * p.len() / 3, "{odd} odd columns of {}", p.len());
    }

    #[test]
    fn residual_from_sums_equals_the_direct_sum() {
        let len = 50;
        let x: Vec<f32> = (0..3 * len).map(|k| ((k * 13 % 37) as f32 * 0.7).cos()).collect();
        let t: Vec<f32> = (0..2 * len).map(|k| ((k * 7 % 23) as f32 * 0.3).sin() + 0.5).collect();
        let mut m = Moments::new(3, 2);
        m.add_planes(&x, &t, len, &(0..len).collect::<Vec<_>>());
        let (mm, c) = ([0.3, -0.2, 0.1, 0.0, 0.5, -0.4], [0.2, -0.1]);
        let direct: f64 = (0..2).map(|i| (0..len).map(|p| {
            let pred = c[i] + (0..3).map(|j| mm[i * 3 + j] * x[j * len + p] as f64).sum::<f64>();
            (t[i * len + p] as f64 - pred).powi(2)
        }).sum::<f64>()).sum();
        assert!((m.residual(&mm, &c) - direct).abs() < 1e-9 * direct.max(1.0), "{} vs {direct}", m.residual(&mm, &c));
    }

    #[test]
    fn recovers_an_exact_linear_map() {
        // t0 = 2 x0 - x1 + 3, t1 = 0.5 x1 - 1 on scattered samples.
        let len = 64;
        let x: Vec<f32> = (0..2 * len).map(|k| ((k * 37 % 101) as f32 / 10.0).sin() * 3.0).collect();
        let t: Vec<f32> = (0..len).map(|p| 2.0 * x[p] - x[len + p] + 3.0).chain((0..len).map(|p| 0.5 * x[len + p] - 1.0)).collect();
        let mut m = Moments::new(2, 2);
        m.add_planes(&x, &t, len, &(0..len).collect::<Vec<_>>());
        let (mm, c) = m.solve(1e-9, None).unwrap();
        for (got, want) in mm.iter().zip([2.0, -1.0, 0.0, 0.5]).chain(c.iter().zip([3.0, -1.0])) {
            assert!((got - want).abs() < 1e-4, "{got} vs {want}");
        }
    }
}
