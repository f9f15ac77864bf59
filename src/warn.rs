//! Warnings: printed on stderr the moment they happen (a user watching a long compile sees
//! them), and kept so the command's report can list every one at its top level.

use std::sync::Mutex;

static KEPT: Mutex<Vec<String>> = Mutex::new(Vec::new());

/// Prints `warning: {msg}` on stderr and keeps `msg` for the report (once: the same
/// warning from two passes reading the same frames is one warning).
pub fn warn(msg: impl Into<String>) {
    let msg = msg.into();
    eprintln!("warning: {msg}");
    let mut kept = KEPT.lock().unwrap_or_else(|e| e.into_inner());
    if !kept.contains(&msg) {
        kept.push(msg);
    }
}

/// Every warning since the last call, in order.
pub fn take() -> Vec<String> {
    std::mem::take(&mut *KEPT.lock().unwrap_or_else(|e| e.into_inner()))
}
