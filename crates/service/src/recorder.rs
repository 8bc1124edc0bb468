//! The service's raw archive: one MCAP file per machine per UTC day (or per size limit),
//! written as `NAME.mcap.partial`, its messages held and written as a chunk after every cycle
//! (or every 16 KiB of them), renamed when closed. Partial files
//! left by a crash are recovered at start: their complete chunks are copied into a closed file.

use driftwatch_core::units;
use std::fs;
use std::io::BufWriter;
use std::path::{Path, PathBuf};

use serde::Serialize;
use thiserror::Error;

use driftwatch_core::recording::{self as rec, Recording};
use driftwatch_recording::mcap_io::{
    ChunkCompression, ReadOptions, RecordingError, RecordingWriter, read_file,
};

/// A machine's messages are written to its file as a chunk at each flush or once their
/// payloads reach this many bytes. A crash loses at most these, as it lost an open chunk (up
/// to 1 MiB) before. 16 KiB, not an lz4 block's 64 KiB: what a machine holds between cycles
/// is memory every machine of a plant keeps (heaptrack, `nc_push` machines through a week:
/// 54 KB a machine held at the peak at 64 KiB, 24 KB at 16 KiB; the files 2.5 % larger).
const HELD_BYTES: usize = 16 * 1024;

#[derive(Debug, Error)]
pub enum RecorderError {
    #[error("recording directory {path}: {source}")]
    Dir {
        path: String,
        source: std::io::Error,
    },
    #[error("recording {path}: {source}")]
    Recording {
        path: String,
        source: RecordingError,
    },
    #[error("renaming {from} to {to}: {source}")]
    Rename {
        from: String,
        to: String,
        source: std::io::Error,
    },
}

/// Files a write closed and opened on the way (a new UTC day or the size limit), and the
/// files of writers that had failed, recovered before it.
#[derive(Debug, Clone, PartialEq, Eq, Default)]
pub struct Rotation {
    pub recovered: Vec<ClosedFile>,
    pub closed: Option<ClosedFile>,
    pub opened: Option<PathBuf>,
}

/// A file the recorder closed or recovered.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct ClosedFile {
    /// The `.partial` name it was written under.
    pub partial: PathBuf,
    pub path: PathBuf,
    pub messages: u64,
    pub recovered: bool,
}

struct OpenFile {
    /// UTC day of the file (days since the epoch), compared per message.
    day_number: i64,
    partial: PathBuf,
    writer: RecordingWriter<BufWriter<fs::File>>,
    messages: u64,
    bytes_hint: u64,
}

/// Writes one machine's recording files under `dir`.
pub struct Recorder {
    dir: PathBuf,
    machine: String,
    max_bytes: u64,
    open: Option<OpenFile>,
    /// Written at the start of every file, so each file stands alone.
    info: rec::MachineInfo,
    /// A writer failed (a full disk): the MCAP writer refuses every write after a failed
    /// one, so it was dropped and its `.partial` file waits to be recovered, up to its last
    /// complete chunk, before the next write opens a new file.
    salvage: bool,
}

fn day_of(t_ns: i64) -> String {
    chrono::DateTime::from_timestamp_nanos(t_ns)
        .format("%Y-%m-%d")
        .to_string()
}

impl Recorder {
    pub fn new(dir: &Path, info: rec::MachineInfo, max_bytes: u64) -> Result<Self, RecorderError> {
        let dir = dir.join(&info.machine_id);
        fs::create_dir_all(&dir).map_err(|source| RecorderError::Dir {
            path: dir.display().to_string(),
            source,
        })?;
        Ok(Recorder {
            dir,
            machine: info.machine_id.clone(),
            max_bytes,
            open: None,
            info,
            salvage: false,
        })
    }

    /// The current writer failed: drop it (what of its file is complete stays readable) and
    /// recover its file before the next write.
    fn broke(&mut self) {
        self.open = None;
        self.salvage = true;
    }

    pub fn machine(&self) -> &str {
        &self.machine
    }

    /// Recover every `.partial` file left in this machine's directory (a crash): copy its
    /// complete chunks into a closed file beside it and remove the partial one.
    pub fn recover(&self) -> Result<Vec<ClosedFile>, RecorderError> {
        let mut out = Vec::new();
        let entries = fs::read_dir(&self.dir).map_err(|source| RecorderError::Dir {
            path: self.dir.display().to_string(),
            source,
        })?;
        let mut partials: Vec<PathBuf> = entries
            .filter_map(|e| e.ok().map(|e| e.path()))
            .filter(|p| p.extension().is_some_and(|x| x == "partial"))
            .collect();
        partials.sort();
        for partial in partials {
            let rec_err = |source| RecorderError::Recording {
                path: partial.display().to_string(),
                source,
            };
            let recording = match read_file(
                &partial,
                &ReadOptions {
                    recover_truncated: true,
                    keep_raw: true,
                },
            ) {
                Ok(r) => r,
                // Nothing readable (cut inside the header): keep it aside for a human.
                Err(RecordingError::NotMcap { .. }) | Err(RecordingError::Truncated { .. }) => {
                    let aside = partial.with_extension("unreadable");
                    fs::rename(&partial, &aside).map_err(|source| RecorderError::Rename {
                        from: partial.display().to_string(),
                        to: aside.display().to_string(),
                        source,
                    })?;
                    continue;
                }
                Err(e) => return Err(rec_err(e)),
            };
            let target = self.free_name(&partial.with_extension(""));
            let messages = rewrite(&recording, &target).map_err(|source| {
                // A copy cut short (a full disk) is no file: the partial one stays.
                let _ = fs::remove_file(&target);
                RecorderError::Recording {
                    path: target.display().to_string(),
                    source,
                }
            })?;
            fs::remove_file(&partial).map_err(|source| RecorderError::Dir {
                path: partial.display().to_string(),
                source,
            })?;
            out.push(ClosedFile {
                partial: partial.clone(),
                path: target,
                messages,
                recovered: true,
            });
        }
        Ok(out)
    }

    /// A name beside `want` that is not taken (a recovered file never overwrites another).
    fn free_name(&self, want: &Path) -> PathBuf {
        if !want.exists() {
            return want.to_path_buf();
        }
        let stem = want
            .file_stem()
            .and_then(|s| s.to_str())
            .unwrap_or("file")
            .to_string();
        (1..)
            .map(|i| want.with_file_name(format!("{stem}.{i}.mcap")))
            .find(|p| !p.exists())
            .unwrap_or_else(|| want.to_path_buf())
    }

    /// Append one message stamped `t_ns`; opens a new file when the UTC day of `clock_ns` (the
    /// service's clock, not the message's stamp: a few badly stamped events from a gateway
    /// must not open files named 1970-01-01 or 2262-04-11) changes, or at the size limit.
    pub fn write<T: Serialize>(
        &mut self,
        topic: &str,
        t_ns: i64,
        clock_ns: i64,
        msg: &T,
    ) -> Result<Rotation, RecorderError> {
        let day_number = clock_ns.div_euclid(units::NS_PER_DAY);
        let mut rotation = Rotation::default();
        if self.salvage {
            rotation.recovered = self.recover()?;
            self.salvage = false;
        }
        let rotate = match &self.open {
            Some(f) => f.day_number != day_number || f.bytes_hint >= self.max_bytes,
            None => true,
        };
        if rotate {
            rotation.closed = self.close()?;
            if let Err(e) = self.open_file(&day_of(clock_ns), clock_ns) {
                self.broke();
                return Err(e);
            }
            rotation.opened = self.current().map(Path::to_path_buf);
        }
        let Some(f) = self.open.as_mut() else {
            return Ok(rotation);
        };
        let data = serde_json::to_vec(msg).map_err(|e| RecorderError::Recording {
            path: f.partial.display().to_string(),
            source: RecordingError::Json {
                topic: topic.to_string(),
                detail: e.to_string(),
            },
        })?;
        if let Err(source) = f.writer.write_json_bytes(topic, t_ns, &data) {
            let path = f.partial.display().to_string();
            self.broke();
            return Err(RecorderError::Recording { path, source });
        }
        f.messages += 1;
        f.bytes_hint += data.len() as u64;
        Ok(rotation)
    }

    fn open_file(&mut self, day: &str, t_ns: i64) -> Result<(), RecorderError> {
        let base = self.free_name(&self.dir.join(format!("{day}.mcap")));
        let partial = base.with_extension("mcap.partial");
        // lz4, not zstd: a writer stays open all day for every machine, and zstd's context
        // (some 3.6 MB each) would be most of a plant's memory. The messages are held back
        // until each flush (a cycle's end) or HELD_BYTES: an open lz4 chunk alone holds some
        // 200 KB of the compressor's buffers, more than a machine's messages between cycles.
        let mut writer = RecordingWriter::create_file_with(&partial, ChunkCompression::Lz4)
            .map_err(|source| RecorderError::Recording {
                path: partial.display().to_string(),
                source,
            })?
            .hold_up_to(HELD_BYTES);
        writer
            .write(rec::TOPIC_INFO, t_ns, &self.info)
            .map_err(|source| RecorderError::Recording {
                path: partial.display().to_string(),
                source,
            })?;
        self.open = Some(OpenFile {
            day_number: t_ns.div_euclid(units::NS_PER_DAY),
            partial,
            writer,
            messages: 1,
            bytes_hint: 0,
        });
        Ok(())
    }

    /// The path of the file being written, if any.
    pub fn current(&self) -> Option<&Path> {
        self.open.as_ref().map(|f| f.partial.as_path())
    }

    /// Close the current chunk so that a crash loses nothing written so far.
    pub fn flush(&mut self) -> Result<(), RecorderError> {
        if let Some(f) = self.open.as_mut()
            && let Err(source) = f.writer.flush()
        {
            let path = f.partial.display().to_string();
            self.broke();
            return Err(RecorderError::Recording { path, source });
        }
        Ok(())
    }

    /// Finish the current file and rename it from `.partial`.
    pub fn close(&mut self) -> Result<Option<ClosedFile>, RecorderError> {
        let Some(f) = self.open.take() else {
            return Ok(None);
        };
        if let Err(source) = f.writer.finish() {
            self.salvage = true;
            return Err(RecorderError::Recording {
                path: f.partial.display().to_string(),
                source,
            });
        }
        let done = f.partial.with_extension("");
        fs::rename(&f.partial, &done).map_err(|source| RecorderError::Rename {
            from: f.partial.display().to_string(),
            to: done.display().to_string(),
            source,
        })?;
        Ok(Some(ClosedFile {
            partial: f.partial.clone(),
            path: done,
            messages: f.messages,
            recovered: false,
        }))
    }
}

/// Copy every message a reader took from a recording, as written and in file order, into a
/// new, closed file.
fn rewrite(r: &Recording, path: &Path) -> Result<u64, RecordingError> {
    let mut w = RecordingWriter::create_file(path)?;
    for m in &r.raw {
        w.write_json_bytes(&m.topic, m.t_ns, &m.data)?;
    }
    w.finish()?;
    Ok(r.raw.len() as u64)
}

#[cfg(test)]
mod tests {
    use super::*;
    use driftwatch_core::recording::SpindleMsg;

    fn dir(name: &str) -> PathBuf {
        let d =
            std::env::temp_dir().join(format!("driftwatch-recorder-{}-{name}", std::process::id()));
        let _ = fs::remove_dir_all(&d);
        d
    }

    fn info() -> rec::MachineInfo {
        rec::MachineInfo {
            machine_id: "m1".into(),
            kinematics: "table_bc".into(),
            software: "test".into(),
        }
    }

    const DAY: i64 = units::NS_PER_DAY;

    #[test]
    fn one_file_per_day_renamed_when_closed() {
        let d = dir("days");
        let mut r = Recorder::new(&d, info(), 1 << 30).unwrap();
        let t0 = 20_000 * DAY + units::NS_PER_H;
        r.write(rec::TOPIC_SPINDLE, t0, t0, &SpindleMsg { rpm: 1000.0 })
            .unwrap();
        assert!(
            r.current()
                .unwrap()
                .to_string_lossy()
                .ends_with(".mcap.partial")
        );
        let closed = r
            .write(
                rec::TOPIC_SPINDLE,
                t0 + DAY,
                t0 + DAY,
                &SpindleMsg { rpm: 0.0 },
            )
            .unwrap()
            .closed
            .unwrap();
        assert_eq!(closed.messages, 2);
        assert!(closed.path.to_string_lossy().ends_with(".mcap"));
        let back = read_file(&closed.path, &ReadOptions::default()).unwrap();
        assert_eq!(back.spindle.len(), 1);
        assert_eq!(back.info.unwrap().machine_id, "m1");
        let last = r.close().unwrap().unwrap();
        assert_ne!(last.path, closed.path);
    }

    #[test]
    fn files_follow_the_service_clock_not_the_stamps() {
        let d = dir("clock");
        let mut r = Recorder::new(&d, info(), 1 << 30).unwrap();
        let now = 20_000 * DAY + units::NS_PER_H;
        // A gateway's bad stamps: the epoch and the end of i64 nanoseconds.
        for t in [now, 0, i64::MAX - 1, now + 1] {
            let rot = r
                .write(rec::TOPIC_SPINDLE, t, now, &SpindleMsg { rpm: 1.0 })
                .unwrap();
            assert!(rot.closed.is_none(), "stamp {t} rotated the file");
        }
        let f = r.close().unwrap().unwrap();
        assert_eq!(
            f.path.file_name().unwrap().to_string_lossy(),
            format!("{}.mcap", day_of(now))
        );
        assert_eq!(f.messages, 5);
        let names: Vec<_> = fs::read_dir(d.join("m1"))
            .unwrap()
            .map(|e| e.unwrap().file_name())
            .collect();
        assert_eq!(names.len(), 1, "{names:?}");
    }

    #[test]
    fn a_partial_file_left_by_a_crash_is_recovered_up_to_its_last_flush() {
        let d = dir("crash");
        let partial;
        {
            let mut r = Recorder::new(&d, info(), 1 << 30).unwrap();
            let t0 = 20_000 * DAY;
            for i in 0..50 {
                r.write(
                    rec::TOPIC_SPINDLE,
                    t0 + i,
                    t0,
                    &SpindleMsg { rpm: i as f64 },
                )
                .unwrap();
            }
            r.write(
                rec::TOPIC_COMPENSATION,
                t0 + 50,
                t0,
                &serde_json::json!({"version": 1}),
            )
            .unwrap();
            r.flush().unwrap();
            for i in 50..60 {
                r.write(
                    rec::TOPIC_SPINDLE,
                    t0 + i,
                    t0,
                    &SpindleMsg { rpm: i as f64 },
                )
                .unwrap();
            }
            partial = r.current().unwrap().to_path_buf();
            // A crash: the writer is leaked, never finished.
            std::mem::forget(r);
        }
        let r = Recorder::new(&d, info(), 1 << 30).unwrap();
        let rec = r.recover().unwrap();
        assert_eq!(rec.len(), 1);
        assert!(rec[0].recovered);
        assert!(!partial.exists());
        let back = read_file(&rec[0].path, &ReadOptions::default()).unwrap();
        assert!(back.spindle.len() >= 50, "{}", back.spindle.len());
        // Topics the reader does not interpret are copied too (the served sets' audit trail).
        assert_eq!(back.other_topics.get(rec::TOPIC_COMPENSATION), Some(&1));
    }
}
