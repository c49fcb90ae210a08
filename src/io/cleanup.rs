//! Temporary output files that must not outlive the process: registered while being
//! written, removed on SIGINT / SIGTERM before the process exits with 130 / 143
//! (128 + signal, as shells report it), and left over from killed runs removed when
//! the same output is written again.

use std::path::{Path, PathBuf};
use std::sync::{Mutex, Once};

static TEMP_FILES: Mutex<Vec<PathBuf>> = Mutex::new(Vec::new());
static HANDLER: Once = Once::new();

fn files() -> std::sync::MutexGuard<'static, Vec<PathBuf>> {
    TEMP_FILES.lock().unwrap_or_else(|e| e.into_inner())
}

/// Removes `path` if the process is interrupted or terminated before [`release`].
pub fn register(path: &Path) {
    HANDLER.call_once(install_handler);
    files().push(path.to_path_buf());
}

/// `path` was renamed into place or removed: no longer ours to clean.
pub fn release(path: &Path) {
    files().retain(|p| p != path);
}

/// A thread that waits for SIGINT / SIGTERM, removes every registered file and exits.
fn install_handler() {
    use signal_hook::consts::{SIGINT, SIGTERM};
    let Ok(mut signals) = signal_hook::iterator::Signals::new([SIGINT, SIGTERM]) else {
        return; // no handler: temporary files are then cleaned by the next run
    };
    std::thread::spawn(move || {
        if let Some(signal) = signals.forever().next() {
            for path in files().iter() {
                let _ = std::fs::remove_file(path);
            }
            std::process::exit(128 + signal);
        }
    });
}

/// Removes `.NAME.PID.tmp` files beside `target` left by processes that no longer run
/// (killed with SIGKILL, power loss). Files of live processes are left alone.
pub fn remove_stale(dir: &Path, name: &str) {
    if !cfg!(target_os = "linux") {
        return; // liveness is read from /proc
    }
    let Ok(entries) = std::fs::read_dir(dir) else {
        return;
    };
    let prefix = format!(".{name}.");
    for entry in entries.flatten() {
        let file = entry.file_name();
        let Some(pid) = file
            .to_str()
            .and_then(|f| f.strip_prefix(&prefix))
            .and_then(|f| f.strip_suffix(".tmp"))
            .and_then(|p| p.parse::<u32>().ok())
        else {
            continue;
        };
        if pid != std::process::id() && !Path::new(&format!("/proc/{pid}")).exists() {
            let _ = std::fs::remove_file(entry.path());
        }
    }
}
