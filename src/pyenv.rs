//! The cache's Python environments for the work Rust hands to Python: RKNN-Toolkit2 (its own
//! pins) and PyTorch for training. One venv serves both: the toolkit already needs torch, and
//! a second multi-GB install would double CI's set-up time.

use anyhow::{anyhow, bail, Context, Result};
use std::path::{Path, PathBuf};
use std::process::Command;

/// The toolkit venv's requirements (one file, which `scripts/setup-toolkit` installs too).
const REQUIREMENTS: &str = include_str!("toolkit-requirements.txt");
const STAMP: &str = ".installed-rknn-toolkit2-2.5.0-train";

/// The pins of [`REQUIREMENTS`], comments and blank lines left out.
fn requirements() -> impl Iterator<Item = &'static str> {
    REQUIREMENTS.lines().map(str::trim).filter(|l| !l.is_empty() && !l.starts_with('#'))
}

/// The toolkit venv's Python, installing it on first use (`PDI_RKNN_PYTHON` overrides).
pub fn toolkit_python() -> Result<PathBuf> {
    if let Some(p) = std::env::var_os("PDI_RKNN_PYTHON") {
        return Ok(PathBuf::from(p));
    }
    let venv = cache()?.join("rknn-env");
    let python = venv.join("bin/python");
    if venv.join(STAMP).exists() {
        return Ok(python);
    }
    let imports = |p: &Path| Command::new(p).args(["-c", "import rknn.api, PIL, pycocotools"]).output().is_ok_and(|o| o.status.success());
    if !(python.exists() && imports(&python)) {
        eprintln!("installing rknn-toolkit2 2.5.0 and torch into {} (first use: ~6 min, ~6 GB)", venv.display());
        let base = std::env::var_os("PDI_RKNN_BASE_PYTHON").map(PathBuf::from).unwrap_or_else(|| PathBuf::from("python3.11"));
        let run = |cmd: &mut Command, what: &str| -> Result<()> {
            let s = cmd.status().with_context(|| format!("{what}: cannot start it"))?;
            if !s.success() {
                bail!("{what} failed ({s})");
            }
            Ok(())
        };
        if !python.exists() {
            run(Command::new(&base).args(["-m", "venv"]).arg(&venv), "creating the rknn-toolkit2 venv (it needs Python 3.11: install python3.11 or set PDI_RKNN_BASE_PYTHON)")?;
        }
        let started = std::time::Instant::now();
        let mut pip = Command::new(venv.join("bin/pip")).args(["install", "-q", "--disable-pip-version-check"]).args(requirements()).spawn().context("pip install rknn-toolkit2==2.5.0: cannot start it")?;
        // pip -q is silent for minutes: say that it is still working.
        let status = loop {
            if let Some(s) = pip.try_wait()? {
                break s;
            }
            std::thread::sleep(std::time::Duration::from_secs(1));
            let t = started.elapsed().as_secs();
            if t > 0 && t.is_multiple_of(30) {
                eprintln!("  still installing ({t} s; {:.1} GB so far)", dir_bytes(&venv) as f64 / 1e9);
            }
        };
        if !status.success() {
            bail!("pip install rknn-toolkit2==2.5.0 failed ({status})");
        }
        if !imports(&python) {
            bail!("rknn-toolkit2 installed into {} but does not import; delete that folder and retry", venv.display());
        }
        eprintln!("installed rknn-toolkit2 2.5.0 and torch: {:.1} GB in {:.0} s", dir_bytes(&venv) as f64 / 1e9, started.elapsed().as_secs_f64());
    }
    std::fs::write(venv.join(STAMP), b"")?;
    Ok(python)
}

/// A Python with torch, onnx and onnxruntime for training workers: `PDI_TORCH_PYTHON`, or the
/// toolkit venv (installed on first use).
pub fn torch_python() -> Result<PathBuf> {
    match std::env::var_os("PDI_TORCH_PYTHON") {
        Some(p) => Ok(PathBuf::from(p)),
        None => toolkit_python(),
    }
}

/// Runs the torch worker `script` (a file already in `dir`, `torch::run` writes them) with
/// `args`: the JSON events on its stdout go to `on_event`; returns its `done`
/// event, or fails with the last line of its stderr. With `ranks` above 1 the worker runs
/// as one torch.distributed job on this machine, through torchrun's launcher (its rank 0
/// reports).
pub fn run_worker(dir: &Path, script: &str, args: &[&std::ffi::OsStr], ranks: usize, on_event: impl FnMut(&serde_json::Value)) -> Result<serde_json::Value> {
    run_python(&torch_python()?, dir, script, args, ranks, None, on_event)
}

/// [`run_worker`] with another Python (the toolkit's), run in `dir`; with `log`, every line
/// it prints that is not an event goes to that file (the toolkit's own account).
pub fn run_python(python: &Path, dir: &Path, script: &str, args: &[&std::ffi::OsStr], ranks: usize, log: Option<&Path>, mut on_event: impl FnMut(&serde_json::Value)) -> Result<serde_json::Value> {
    use std::io::{BufRead, BufReader, Write};
    use std::process::Stdio;
    let mut log = log.map(|p| std::fs::File::create(p).with_context(|| format!("cannot write {}", p.display()))).transpose()?;
    let _turn = exclusive()?;
    let mut command = Command::new(python);
    if ranks > 1 {
        command.args(["-m", "torch.distributed.run", "--standalone", "--nnodes", "1", "--nproc-per-node"]).arg(ranks.to_string());
    }
    let mut child = command
        .arg(dir.join(script))
        .args(args)
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .current_dir(dir)
        .spawn()
        .with_context(|| format!("cannot run {}", python.display()))?;
    let stderr = child.stderr.take().expect("piped");
    let mut stderr_log = log.as_ref().map(|f| f.try_clone()).transpose()?;
    let errors = std::thread::spawn(move || {
        let text = std::io::read_to_string(stderr).unwrap_or_default();
        if let Some(f) = stderr_log.as_mut() {
            let _ = f.write_all(text.as_bytes());
        }
        text
    });
    let mut done = None;
    for line in BufReader::new(child.stdout.take().expect("piped")).lines() {
        let line = line?;
        let event = match serde_json::from_str::<serde_json::Value>(&line) {
            Ok(e) if e.get("event").is_some() => e,
            _ => {
                if let Some(f) = log.as_mut() {
                    writeln!(f, "{line}")?;
                }
                continue;
            }
        };
        if event["event"] == "done" {
            done = Some(event);
            // Everything is written before `done`: what follows is the ranks' shutdown.
            if ranks > 1 {
                break;
            }
        } else {
            on_event(&event);
        }
    }
    if let Some(d) = done.take_if(|_| ranks > 1) {
        return finish(&mut child, ranks, SHUTDOWN).map(|()| d);
    }
    let status = child.wait()?;
    let err = errors.join().unwrap_or_default();
    match done.filter(|_| status.success()) {
        Some(d) => Ok(d),
        None => bail!("{script} failed ({status}): {}", err.lines().rev().find(|l| !l.trim().is_empty()).unwrap_or("no message")),
    }
}

/// How long a distributed job that reported `done` may take to exit.
const SHUTDOWN: std::time::Duration = std::time::Duration::from_secs(120);

/// Waits for a torch.distributed job that has reported `done`. Its teardown can hang (the
/// ranks' last barrier or `destroy_process_group`, a known gloo flake) although its results
/// are on disk by then: past `grace` the launcher is asked to stop its ranks (SIGTERM, which
/// torchrun passes on), then past another `grace` killed, with a warning, and the run stands.
fn finish(child: &mut std::process::Child, ranks: usize, grace: std::time::Duration) -> Result<()> {
    let exited = |child: &mut std::process::Child, within: std::time::Duration| -> Result<Option<std::process::ExitStatus>> {
        let start = std::time::Instant::now();
        while start.elapsed() < within {
            if let Some(status) = child.try_wait()? {
                return Ok(Some(status));
            }
            std::thread::sleep(std::time::Duration::from_millis(100));
        }
        Ok(None)
    };
    match exited(child, grace)? {
        Some(status) if status.success() => return Ok(()),
        Some(status) => crate::warn::warn(format!("the {ranks} training ranks reported their result, then exited with {status}")),
        None => {
            crate::warn::warn(format!("the {ranks} training ranks reported their result but did not exit within {} s: stopped", grace.as_secs_f32()));
            // SAFETY: a signal to this function's own child, which has not been reaped.
            unsafe { libc::kill(child.id() as libc::pid_t, libc::SIGTERM) };
            if exited(child, grace)?.is_none() {
                child.kill()?;
                child.wait()?;
            }
        }
    }
    Ok(())
}

/// With `PDI_WORKER_LOCK` naming a file, the Python workers that take every core (trainings,
/// the toolkit) take turns across all the processes naming it: two trainings on the same
/// cores slow each other several-fold (a QAT test: 38 s alone, 421 s beside another). With
/// `PDI_WORKER_SLOTS=N` as well, N turns run side by side, each training on its share of the
/// cores ([`worker_share`]): on small models one thread trains nearly as fast as two, so two
/// one-thread trainings do more in the same time than two-thread ones one after the other.
/// The turn ends when the returned file is dropped; without the variable there is no lock.
pub fn exclusive() -> Result<Option<std::fs::File>> {
    let Some(path) = std::env::var_os("PDI_WORKER_LOCK") else { return Ok(None) };
    turn(Path::new(&path), worker_slots()?).map(Some)
}

/// One of `slots` turns on the lock files `path` (slot 0), `path.1`, …: the first free one,
/// waiting until one is free.
fn turn(path: &Path, slots: usize) -> Result<std::fs::File> {
    use std::os::fd::AsRawFd;
    let open = |p: &Path| std::fs::OpenOptions::new().create(true).truncate(false).write(true).open(p).with_context(|| format!("PDI_WORKER_LOCK: cannot open {}", p.display()));
    // SAFETY: flock on a descriptor this function owns.
    let lock = |f: &std::fs::File, how: libc::c_int| unsafe { libc::flock(f.as_raw_fd(), how) } == 0;
    if slots == 1 {
        let file = open(path)?;
        if !lock(&file, libc::LOCK_EX) {
            bail!("PDI_WORKER_LOCK: cannot lock {}: {}", path.display(), std::io::Error::last_os_error());
        }
        return Ok(file);
    }
    let slot = |k: usize| {
        let mut name = path.as_os_str().to_owned();
        name.push(format!(".{k}"));
        PathBuf::from(name)
    };
    let mut files = (0..slots).map(|k| if k == 0 { open(path) } else { open(&slot(k)) }).collect::<Result<Vec<_>>>()?;
    loop {
        for k in 0..slots {
            if lock(&files[k], libc::LOCK_EX | libc::LOCK_NB) {
                return Ok(files.swap_remove(k));
            }
            let e = std::io::Error::last_os_error();
            if e.raw_os_error() != Some(libc::EWOULDBLOCK) {
                bail!("PDI_WORKER_LOCK: cannot lock {}: {e}", path.display());
            }
        }
        std::thread::sleep(std::time::Duration::from_millis(50));
    }
}

/// `PDI_WORKER_SLOTS`: how many workers' turns run at once (1 unless set with
/// `PDI_WORKER_LOCK`).
fn worker_slots() -> Result<usize> {
    if std::env::var_os("PDI_WORKER_LOCK").is_none() {
        return Ok(1);
    }
    match std::env::var("PDI_WORKER_SLOTS") {
        Err(std::env::VarError::NotPresent) => Ok(1),
        Ok(v) => match v.trim().parse::<usize>() {
            Ok(n) if (1..=64).contains(&n) => Ok(n),
            _ => bail!("PDI_WORKER_SLOTS: expected a count from 1 to 64, got {v:?}"),
        },
        Err(_) => bail!("PDI_WORKER_SLOTS: not valid UTF-8"),
    }
}

/// The cores one worker's turn has: every core of this machine, divided among the turns that
/// run at once ([`exclusive`]); at least one. A training whose recipe leaves `threads` at 0
/// trains on this many (the manifest records it).
pub fn worker_share() -> usize {
    let cores = std::thread::available_parallelism().map_or(1, |n| n.get());
    (cores / worker_slots().unwrap_or(1)).max(1)
}

/// Bytes under `dir` (files only; links not followed).
fn dir_bytes(dir: &Path) -> u64 {
    let mut total = 0;
    let mut stack = vec![dir.to_path_buf()];
    while let Some(d) = stack.pop() {
        for e in std::fs::read_dir(&d).into_iter().flatten().flatten() {
            match e.file_type() {
                Ok(t) if t.is_dir() => stack.push(e.path()),
                Ok(t) if t.is_file() => total += e.metadata().map_or(0, |m| m.len()),
                _ => {}
            }
        }
    }
    total
}

/// The cache folder, as `scripts/setup` chooses it: `PDI_CACHE`, else `pdi-compile` in
/// `XDG_CACHE_HOME` or `~/.cache`.
pub fn cache() -> Result<PathBuf> {
    let set = |k: &str| std::env::var_os(k).filter(|v| !v.is_empty()).map(PathBuf::from);
    set("PDI_CACHE")
        .or_else(|| set("XDG_CACHE_HOME").map(|c| c.join("pdi-compile")))
        .or_else(|| set("HOME").map(|h| h.join(".cache/pdi-compile")))
        .ok_or_else(|| anyhow!("set PDI_CACHE or HOME: Python environments are installed into a cache folder"))
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::time::{Duration, Instant};

    fn sh(script: &str) -> std::process::Child {
        Command::new("sh").args(["-c", script]).spawn().unwrap()
    }

    #[test]
    fn turns_run_as_many_at_once_as_there_are_slots() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("worker.lock");
        let (a, b) = (turn(&path, 2).unwrap(), turn(&path, 2).unwrap());
        // A third waits until one of the two ends.
        let (tx, rx) = std::sync::mpsc::channel();
        let p = path.clone();
        std::thread::spawn(move || tx.send(turn(&p, 2).map(|_| ()).is_ok()).unwrap());
        assert!(rx.recv_timeout(Duration::from_millis(400)).is_err(), "a third turn ran beside two");
        drop(b);
        assert!(rx.recv_timeout(Duration::from_secs(5)).unwrap());
        drop(a);
        // One slot: the file itself, as before.
        let one = turn(&path, 1).unwrap();
        let (tx, rx) = std::sync::mpsc::channel();
        std::thread::spawn(move || tx.send(turn(&path, 1).is_ok()).unwrap());
        assert!(rx.recv_timeout(Duration::from_millis(400)).is_err(), "two turns with one slot");
        drop(one);
        assert!(rx.recv_timeout(Duration::from_secs(5)).unwrap());
    }

    #[test]
    fn a_job_that_does_not_exit_after_done_is_stopped() {
        let grace = Duration::from_millis(300);
        let start = Instant::now();
        // Exits on SIGTERM, like torchrun.
        finish(&mut sh("exec sleep 60"), 2, grace).unwrap();
        // Ignores it: killed.
        let mut deaf = sh("trap '' TERM; sleep 60; sleep 60");
        finish(&mut deaf, 2, grace).unwrap();
        assert!(deaf.try_wait().unwrap().is_some());
        assert!(start.elapsed() < Duration::from_secs(10), "{:?}", start.elapsed());
        // A job that exits on its own is waited for.
        let mut quick = sh("sleep 0.1");
        finish(&mut quick, 2, Duration::from_secs(30)).unwrap();
        assert!(quick.try_wait().unwrap().unwrap().success());
    }
}
