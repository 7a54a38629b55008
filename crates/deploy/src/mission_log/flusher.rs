//! The thread that finishes the open chunk and flushes a log every flush period.

use std::fs::File;
use std::io::BufWriter;
use std::path::Path;
use std::sync::mpsc::{self, RecvTimeoutError};
use std::sync::{Arc, Mutex};
use std::thread::JoinHandle;

use foxglove::McapWriterHandle;

use super::FLUSH_PERIOD;

/// The background flush: stops when its sender is dropped.
pub(super) struct Flusher {
    stop: Option<mpsc::Sender<()>>,
    thread: Option<JoinHandle<()>>,
    /// The first flush error, reported by the next write.
    pub(super) error: Arc<Mutex<Option<String>>>,
}

impl Drop for Flusher {
    fn drop(&mut self) {
        self.stop.take();
        if let Some(thread) = self.thread.take() {
            // A panic in the flusher is already reported by the thread; nothing to add here.
            let _ = thread.join();
        }
    }
}

impl Flusher {
    pub(super) fn spawn(
        path: &Path,
        writer: Arc<McapWriterHandle<BufWriter<File>>>,
    ) -> Result<Self, String> {
        let (stop, stopped) = mpsc::channel::<()>();
        let error = Arc::new(Mutex::new(None));
        let first_error = Arc::clone(&error);
        let name = format!(
            "log-flush {}",
            path.file_name().map_or("".into(), |n| n.to_string_lossy())
        );
        let thread = std::thread::Builder::new()
            .name(name)
            .spawn(move || loop {
                match stopped.recv_timeout(FLUSH_PERIOD) {
                    Err(RecvTimeoutError::Timeout) => {
                        if let Err(e) = writer.flush() {
                            let mut slot = first_error.lock().unwrap_or_else(|p| p.into_inner());
                            slot.get_or_insert_with(|| e.to_string());
                        }
                    }
                    // Stopped (the sender is dropped): the owner finishes the file.
                    Ok(()) | Err(RecvTimeoutError::Disconnected) => return,
                }
            })
            .map_err(|e| format!("cannot start the flush thread: {e}"))?;
        Ok(Self {
            stop: Some(stop),
            thread: Some(thread),
            error,
        })
    }
}
