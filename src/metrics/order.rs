//! Order statistics of timings: one rule for every median and percentile the tool reports.

/// The value at quantile `q` (0 to 1) of `sorted` (ascending), by nearest rank; 0 when empty.
pub fn quantile(sorted: &[f64], q: f64) -> f64 {
    match sorted.len() {
        0 => 0.0,
        n => sorted[((n - 1) as f64 * q.clamp(0.0, 1.0)).round() as usize],
    }
}

/// `values` in ascending order.
pub fn sorted(mut values: Vec<f64>) -> Vec<f64> {
    values.sort_by(f64::total_cmp);
    values
}

/// The median of `values` (the upper one of an even count); 0 when empty.
pub fn median(values: Vec<f64>) -> f64 {
    quantile(&sorted(values), 0.5)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn nearest_rank_and_the_upper_median() {
        assert_eq!(median(vec![3.0, 1.0, 2.0]), 2.0);
        assert_eq!(median(vec![4.0, 1.0, 3.0, 2.0]), 3.0);
        assert_eq!(median(Vec::new()), 0.0);
        let s = sorted((1..=101).map(f64::from).collect());
        assert_eq!((quantile(&s, 0.0), quantile(&s, 0.9), quantile(&s, 1.0)), (1.0, 91.0, 101.0));
    }
}
