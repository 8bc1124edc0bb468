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
    /// What the failed writer held and had not yet written as a complete chunk, oldest first,
    /// and its file: written first into the next file, but for the part that the recovered
    /// file turns out to hold (a chunk that reached the disk before the failure).
    carry: Vec<rec::RawMessage>,
    carry_from: Option<PathBuf>,
    /// Files closed or recovered by a call that then failed: reported by the next call.
    unreported: Vec<ClosedFile>,
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
            carry: Vec::new(),
            carry_from: None,
            unreported: Vec::new(),
        })
    }

    /// The current writer failed: drop it (what of its file is complete stays readable) and
    /// recover its file before the next write.
    fn broke(&mut self) {
        if let Some(mut f) = self.open.take() {
            // The next file writes its own /machine/info.
            let held = f.writer.take_held().into_iter();
            self.carry
                .extend(held.filter(|m| m.topic != rec::TOPIC_INFO));
            self.carry_from = Some(f.partial);
        }
        self.salvage = true;
    }

    pub fn machine(&self) -> &str {
        &self.machine
    }

    /// Recover every `.partial` file left in this machine's directory (a crash): copy its
    /// complete chunks into a closed file beside it and remove the partial one.
    pub fn recover(&mut self) -> Result<Vec<ClosedFile>, RecorderError> {
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
            if self.carry_from.as_ref() == Some(&partial) {
                // What the failed writer held is written again, but for what reached the disk.
                if let Some(last) = recording.raw.last()
                    && let Some(j) = self.carry.iter().position(|m| m == last)
                {
                    self.carry.drain(..=j);
                }
                self.carry_from = None;
            }
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
        // Its file read, or not there to read (unreadable, set aside): nothing more to drop.
        self.carry_from = None;
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
        let mut rotation = Rotation {
            recovered: std::mem::take(&mut self.unreported),
            ..Default::default()
        };
        let result = self
            .ready(&mut rotation, clock_ns)
            .and_then(|()| self.append(topic, t_ns, msg));
        self.settle(rotation, result)
    }

    /// Close the recording for good (the service stops): what a failed writer left is written
    /// first, into a new file, if the disk takes it. Returns every file closed or recovered.
    pub fn stop(&mut self, clock_ns: i64) -> Result<Vec<ClosedFile>, RecorderError> {
        let mut rotation = Rotation {
            recovered: std::mem::take(&mut self.unreported),
            ..Default::default()
        };
        let mut result = Ok(());
        if !self.carry.is_empty() {
            result = self.ready(&mut rotation, clock_ns);
        }
        if result.is_ok() {
            match self.close() {
                Ok(closed) => rotation.recovered.extend(closed),
                Err(e) => result = Err(e),
            }
        }
        let rotation = self.settle(rotation, result)?;
        Ok(rotation
            .recovered
            .into_iter()
            .chain(rotation.closed)
            .collect())
    }

    /// The files a failed call had closed or recovered are reported by the next one: their
    /// store rows must not be forgotten.
    fn settle(
        &mut self,
        rotation: Rotation,
        result: Result<(), RecorderError>,
    ) -> Result<Rotation, RecorderError> {
        match result {
            Ok(()) => Ok(rotation),
            Err(e) => {
                self.unreported = rotation.recovered;
                self.unreported.extend(rotation.closed);
                Err(e)
            }
        }
    }

    /// Recover a failed writer's file, rotate, and write what the failed writer held.
    fn ready(&mut self, rotation: &mut Rotation, clock_ns: i64) -> Result<(), RecorderError> {
        let day_number = clock_ns.div_euclid(units::NS_PER_DAY);
        if self.salvage {
            rotation.recovered.extend(self.recover()?);
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
            return Ok(());
        };
        // What a failed writer held, before anything new.
        let carry = std::mem::take(&mut self.carry);
        for (i, m) in carry.iter().enumerate() {
            if let Err(source) = f.writer.write_json_bytes(&m.topic, m.t_ns, &m.data) {
                let path = f.partial.display().to_string();
                self.broke();
                self.carry.extend_from_slice(&carry[i + 1..]);
                return Err(RecorderError::Recording { path, source });
            }
            f.messages += 1;
            f.bytes_hint += m.data.len() as u64;
        }
        Ok(())
    }

    /// Append one message to the open file.
    fn append<T: Serialize>(
        &mut self,
        topic: &str,
        t_ns: i64,
        msg: &T,
    ) -> Result<(), RecorderError> {
        let Some(f) = self.open.as_mut() else {
            return Ok(());
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
            // The caller writes this message again: it is not carried too.
            if self
                .carry
                .last()
                .is_some_and(|m| m.topic == topic && m.t_ns == t_ns && m.data == data)
            {
                self.carry.pop();
            }
            return Err(RecorderError::Recording { path, source });
        }
        f.messages += 1;
        f.bytes_hint += data.len() as u64;
        Ok(())
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
    fn close(&mut self) -> Result<Option<ClosedFile>, RecorderError> {
        // The held messages first: a failure leaves them to the next file.
        self.flush()?;
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

    fn dir(name: &str) -> (tempfile::TempDir, PathBuf) {
        crate::scratch_dir(&format!("recorder-{name}"))
    }

    fn info() -> rec::MachineInfo {
        rec::MachineInfo {
            machine_id: "m1".into(),
            kinematics: "table_bc".into(),
            software: "test".into(),
        }
    }

    const DAY: i64 = units::NS_PER_DAY;

    /// Every message of a recording directory's closed files, in file order (the files by
    /// their first message).
    fn all_messages(d: &Path) -> Vec<(String, i64, Vec<u8>)> {
        let keep = ReadOptions {
            recover_truncated: false,
            keep_raw: true,
        };
        let mut files: Vec<Vec<rec::RawMessage>> = fs::read_dir(d.join("m1"))
            .unwrap()
            .map(|e| e.unwrap().path())
            .filter(|p| p.extension().is_some_and(|x| x == "mcap"))
            .map(|p| read_file(&p, &keep).unwrap().raw)
            .collect();
        files.sort_by_key(|raw| raw.first().map(|m| m.t_ns));
        files
            .into_iter()
            .flatten()
            .map(|m| (m.topic, m.t_ns, m.data))
            .collect()
    }

    /// The disk is full under a new day's recording (its file is /dev/full): the chunk its
    /// held messages set off fails. Those messages are written into the next file, once and in
    /// order; the message whose write failed is written once, by the caller's retry.
    #[test]
    fn a_full_disk_loses_no_held_message_and_writes_none_twice() {
        let (_tmp, d) = dir("full");
        let mut r = Recorder::new(&d, info(), 1 << 30).unwrap();
        let t0 = 20_000 * DAY + units::NS_PER_H;
        let spin = |r: &mut Recorder, i: i64| {
            let t = t0 + i * units::NS_PER_S;
            r.write(rec::TOPIC_SPINDLE, t, t, &SpindleMsg { rpm: i as f64 })
        };
        spin(&mut r, 0).unwrap();
        let next_day = d
            .join("m1")
            .join(format!("{}.mcap.partial", day_of(t0 + DAY)));
        std::os::unix::fs::symlink("/dev/full", &next_day).unwrap();
        let day = DAY / units::NS_PER_S;
        let mut i = day;
        let failed = loop {
            if spin(&mut r, i).is_err() {
                break i;
            }
            i += 1;
            assert!(
                i < day + 100_000,
                "the held messages never reached the disk"
            );
        };
        assert!(
            failed > day + 100,
            "the limit holds many messages: {}",
            failed - day
        );
        // Room again: the next file is a real one (/dev/full is never read back).
        fs::remove_file(&next_day).unwrap();
        spin(&mut r, failed).unwrap();
        spin(&mut r, failed + 1).unwrap();
        r.close().unwrap();
        let got: Vec<i64> = all_messages(&d)
            .into_iter()
            .filter(|m| m.0 == rec::TOPIC_SPINDLE)
            .map(|m| (m.1 - t0) / units::NS_PER_S)
            .collect();
        let want: Vec<i64> = std::iter::once(0).chain(day..=failed + 1).collect();
        assert_eq!(got, want);
    }

    /// The service stops after a failed write and before any other message: what the failed
    /// writer held is still written, into a file of its own, and reported.
    #[test]
    fn a_stop_after_a_failed_write_writes_what_the_writer_held() {
        let (_tmp, d) = dir("stop");
        let mut r = Recorder::new(&d, info(), 1 << 30).unwrap();
        let t0 = 20_000 * DAY + units::NS_PER_H;
        let t = |i: i64| t0 + DAY + i * units::NS_PER_S;
        let first = r
            .write(rec::TOPIC_SPINDLE, t0, t0, &SpindleMsg { rpm: 0.0 })
            .unwrap();
        assert!(first.opened.is_some());
        let next_day = d.join("m1").join(format!("{}.mcap.partial", day_of(t(0))));
        std::os::unix::fs::symlink("/dev/full", &next_day).unwrap();
        let mut written = Vec::new();
        for i in 0..100_000 {
            let ok = r
                .write(
                    rec::TOPIC_SPINDLE,
                    t(i),
                    t(i),
                    &SpindleMsg { rpm: i as f64 },
                )
                .is_ok();
            if !ok {
                break;
            }
            written.push(t(i));
        }
        assert!(!r.carry.is_empty());
        fs::remove_file(&next_day).unwrap();
        let files = r.stop(t(0) + units::NS_PER_H).unwrap();
        // The first day's file (closed at the rotation) was reported then; now the carry's.
        assert_eq!(files.len(), 1, "{files:?}");
        assert_eq!(
            files[0].messages as usize,
            written.len() + 1,
            "with its info"
        );
        let got: Vec<i64> = all_messages(&d)
            .into_iter()
            .filter(|m| m.0 == rec::TOPIC_SPINDLE)
            .map(|m| m.1)
            .collect();
        assert_eq!(got, std::iter::once(t0).chain(written).collect::<Vec<_>>());
    }

    /// A file recovered by a write that then failed (here on a message that is no JSON) is
    /// reported by the next write: its store row is not forgotten.
    #[test]
    fn a_file_recovered_by_a_failed_write_is_reported_by_the_next() {
        let (_tmp, d) = dir("unreported");
        let t0 = 20_000 * DAY + units::NS_PER_H;
        {
            let mut r = Recorder::new(&d, info(), 1 << 30).unwrap();
            r.write(rec::TOPIC_SPINDLE, t0, t0, &SpindleMsg { rpm: 1.0 })
                .unwrap();
            r.flush().unwrap();
            // A crash: the writer is leaked, never finished.
            std::mem::forget(r);
        }
        let mut r = Recorder::new(&d, info(), 1 << 30).unwrap();
        r.salvage = true;
        let not_json = std::collections::BTreeMap::from([((1, 2), 3)]);
        assert!(
            r.write(rec::TOPIC_SPINDLE, t0 + 1, t0 + 1, &not_json)
                .is_err()
        );
        let next = r
            .write(rec::TOPIC_SPINDLE, t0 + 2, t0 + 2, &SpindleMsg { rpm: 2.0 })
            .unwrap();
        assert_eq!(next.recovered.len(), 1, "{next:?}");
        assert!(next.recovered[0].recovered);
    }

    /// A failed writer's messages that its file turns out to hold (their chunk reached the
    /// disk before the failure) are not written again; the rest are.
    #[test]
    fn carried_messages_that_reached_the_disk_are_not_written_again() {
        let (_tmp, d) = dir("landed");
        let mut r = Recorder::new(&d, info(), 1 << 30).unwrap();
        let t0 = 20_000 * DAY + units::NS_PER_H;
        let msg = |i: i64| rec::RawMessage {
            topic: rec::TOPIC_SPINDLE.to_string(),
            t_ns: t0 + i * units::NS_PER_MIN,
            data: serde_json::to_vec(&SpindleMsg { rpm: i as f64 }).unwrap(),
        };
        for i in 0..3 {
            let m = msg(i);
            r.write(
                rec::TOPIC_SPINDLE,
                m.t_ns,
                m.t_ns,
                &SpindleMsg { rpm: i as f64 },
            )
            .unwrap();
        }
        r.flush().unwrap();
        // As if the writer had failed after messages 1 and 2 reached the disk, holding 1 to 4
        // (the writer is lost as in a crash: its file stays partial).
        let f = r.open.take().unwrap();
        r.carry = (1..5).map(msg).collect();
        r.carry_from = Some(f.partial.clone());
        r.salvage = true;
        std::mem::forget(f);
        let m = msg(5);
        r.write(rec::TOPIC_SPINDLE, m.t_ns, m.t_ns, &SpindleMsg { rpm: 5.0 })
            .unwrap();
        r.close().unwrap();
        let got: Vec<i64> = all_messages(&d)
            .into_iter()
            .filter(|m| m.0 == rec::TOPIC_SPINDLE)
            .map(|m| (m.1 - t0) / units::NS_PER_MIN)
            .collect();
        assert_eq!(got, [0, 1, 2, 3, 4, 5]);
    }

    #[test]
    fn one_file_per_day_renamed_when_closed() {
        let (_tmp, d) = dir("days");
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
        let (_tmp, d) = dir("clock");
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
        let (_tmp, d) = dir("crash");
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
        let mut r = Recorder::new(&d, info(), 1 << 30).unwrap();
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
