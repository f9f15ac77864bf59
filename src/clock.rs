//! Where a pass's time goes, phase by phase, for its report.

use std::time::Instant;

/// Seconds per phase of a pass, for its report (where the time goes is a deployment concern).
pub struct Clock {
    last: Instant,
    pub laps: std::collections::BTreeMap<&'static str, f64>,
}

impl Default for Clock {
    fn default() -> Self {
        Clock { last: Instant::now(), laps: Default::default() }
    }
}

impl Clock {
    /// Books the time since the last lap (or the start) to `phase`, adding to earlier laps of it.
    pub fn lap(&mut self, phase: &'static str) {
        *self.laps.entry(phase).or_default() += self.last.elapsed().as_secs_f64();
        self.last = Instant::now();
    }
}
