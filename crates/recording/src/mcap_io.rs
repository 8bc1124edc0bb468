//! Reading and writing recording-format v1 MCAP files.
//!
//! Writing goes through the `mcap` crate's writer: JSON messages, one JSON Schema per channel,
//! zstd-compressed chunks, message indexes and a summary when finished.
//!
//! Reading walks the file's top-level records itself and uses the `mcap` crate only to
//! decompress and check one complete chunk at a time. That is what makes a cut-short file
//! readable "up to its last complete chunk": a record that runs past the end of the file is
//! recognised as truncation (also the half-written chunk a crashed writer leaves, whose length
//! field is still a placeholder), and a chunk is only used once all of it is present and its
//! CRC matches. It also keeps malformed input away from code paths of `mcap` 0.26 that panic on
//! hostile lengths (see the tests).

use std::collections::HashMap;
use std::fmt::Write as _;
use std::fs::File;
use std::io::{BufWriter, Seek, SeekFrom, Write};
use std::path::{Path, PathBuf};

use mcap::records::{MessageHeader, op};
use mcap::sans_io::{LinearReadEvent, LinearReader, LinearReaderOptions};
use mcap::{Compression, MAGIC, McapError, WriteOptions, Writer};
use serde::Serialize;

use driftwatch_core::recording::{
    CycleResultMsg, DisplacementMsg, MachineInfo, Recording, SpindleMsg, StateMsg, TOPIC_DETECTION,
    TOPIC_DISPLACEMENT, TOPIC_INFO, TOPIC_RESULT, TOPIC_SPINDLE, TOPIC_STATE, TOPIC_TEMPERATURE,
    TemperatureMsg, Timed,
};

/// The topics this reader interprets; every other topic is only counted.
const KNOWN_TOPICS: [&str; 7] = [
    TOPIC_INFO,
    TOPIC_STATE,
    TOPIC_SPINDLE,
    TOPIC_TEMPERATURE,
    TOPIC_DISPLACEMENT,
    TOPIC_DETECTION,
    TOPIC_RESULT,
];

/// The largest uncompressed chunk the reader accepts. Writers use chunks of a few MiB; the cap
/// keeps a damaged size field from allocating gigabytes.
const MAX_CHUNK_BYTES: u64 = 512 * 1024 * 1024;

/// Opcode and length that start every MCAP record.
const RECORD_PREFIX: usize = 1 + 8;

#[derive(Debug, thiserror::Error)]
pub enum RecordingError {
    #[error("cannot {action} {}: {error}", describe_path(.path))]
    Io {
        action: &'static str,
        path: Option<PathBuf>,
        error: std::io::Error,
    },
    #[error("{name} is not an MCAP file ({detail})")]
    NotMcap { name: String, detail: String },
    #[error("{}", truncated_message(*.messages_read, .detail))]
    Truncated { messages_read: u64, detail: String },
    #[error("the recording is damaged: {detail}")]
    Corrupt { detail: String },
    #[error("the recording uses {detail}, which this reader does not support")]
    Unsupported { detail: String },
    #[error(
        "channel {topic} has message encoding '{encoding}', but recording-format v1 requires 'json'"
    )]
    Encoding { topic: String, encoding: String },
    #[error("cannot encode a {topic} message as JSON: {detail}")]
    Json { topic: String, detail: String },
    #[error(
        "cannot record a {topic} message at {t_ns} ns: log times count ns since the Unix epoch and cannot be negative"
    )]
    NegativeTime { topic: String, t_ns: i64 },
    #[error("cannot write the recording: {detail}")]
    Write { detail: String },
}

fn describe_path(path: &Option<PathBuf>) -> String {
    match path {
        Some(p) => p.display().to_string(),
        None => "the recording".to_string(),
    }
}

fn truncated_message(messages_read: u64, detail: &str) -> String {
    match messages_read {
        0 => format!(
            "the recording ends early ({detail}); it holds no complete chunk, so no messages can be read"
        ),
        1 => format!(
            "the recording ends early ({detail}); 1 message in complete chunks could be read; pass --recover to use it"
        ),
        n => format!(
            "the recording ends early ({detail}); {n} messages in complete chunks could be read; pass --recover to use them"
        ),
    }
}

impl RecordingError {
    fn from_mcap_write(e: McapError) -> Self {
        match e {
            McapError::Io(error) => RecordingError::Io {
                action: "write",
                path: None,
                error,
            },
            other => RecordingError::Write {
                detail: other.to_string(),
            },
        }
    }

    fn with_path(self, p: &Path) -> Self {
        match self {
            RecordingError::Io {
                action,
                path: None,
                error,
            } => RecordingError::Io {
                action,
                path: Some(p.to_path_buf()),
                error,
            },
            RecordingError::NotMcap { detail, .. } => RecordingError::NotMcap {
                name: p.display().to_string(),
                detail,
            },
            other => other,
        }
    }
}

// ------------------------------------------------------------------------------------------
// Writing
// ------------------------------------------------------------------------------------------

struct ChannelState {
    id: u16,
    next_sequence: u32,
}

/// Writes a recording-format v1 MCAP file. Channels (with their JSON Schema) are registered the
/// first time a topic is written. Call [`RecordingWriter::finish`] at the end; a writer dropped
/// without it still tries to close the file, but cannot report failure (and one that holds
/// messages back loses them, as a crash would).
pub struct RecordingWriter<W: Write + Seek> {
    inner: Writer<Positioned<W>>,
    channels: HashMap<String, ChannelState>,
    /// Messages kept back from the `mcap` writer, when it holds them (see
    /// [`RecordingWriter::hold_up_to`]).
    held: Option<Held>,
}

/// Messages written but not yet handed to the `mcap` writer. An `mcap` writer holds its open
/// chunk's compressor, some 200 KB for lz4 (its frame's input, dictionary and output
/// buffers), from a chunk's first message until the chunk closes; a writer that holds its
/// messages back and hands them over in one go at each flush holds a compressor only while
/// it writes a chunk, and otherwise only the messages themselves.
struct Held {
    /// Hand the messages over (one chunk) once their payloads reach this many bytes.
    limit: usize,
    messages: Vec<HeldMessage>,
    topics: Vec<String>,
    data: Vec<u8>,
}

/// A held message: its time, its topic (an index into `topics`) and where its payload ends
/// in `data` (it starts where the one before it ends). 16 bytes where a range and an index
/// took 32: a service's loop holds up to 16 KiB of messages, a few hundred of them.
#[derive(Clone, Copy)]
struct HeldMessage {
    time: u64,
    topic: u32,
    end: u32,
}

impl Held {
    /// Each held message's topic, time and payload, oldest first.
    fn each(&self) -> impl Iterator<Item = (&str, u64, &[u8])> {
        let mut start = 0;
        self.messages.iter().map(move |m| {
            let end = m.end as usize;
            let payload = &self.data[start..end];
            start = end;
            (self.topics[m.topic as usize].as_str(), m.time, payload)
        })
    }

    /// The same limit, nothing held.
    fn emptied(self) -> Held {
        Held {
            limit: self.limit,
            messages: Vec::new(),
            topics: Vec::new(),
            data: Vec::new(),
        }
    }
}

/// How a writer compresses its chunks. Every reader of the format takes both.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum ChunkCompression {
    /// zstd: the smallest files, but an open writer holds a compression context of some
    /// 3.6 MB (level 3's window and tables) for as long as its file is open.
    Zstd,
    /// lz4: larger files for a context of some 150 KB: for writers held open by the thousand
    /// (the service's recorder keeps one per machine open all day).
    Lz4,
}

impl<W: Write + Seek> RecordingWriter<W> {
    /// Starts a recording on `w`: zstd chunks of the default size, compressed on the calling
    /// thread (the `mcap` default would start a zstd worker per physical CPU).
    pub fn new(w: W) -> Result<Self, RecordingError> {
        Self::with_compression(w, ChunkCompression::Zstd)
    }

    /// Starts a recording on `w` with chunks compressed as `compression` says.
    pub fn with_compression(w: W, compression: ChunkCompression) -> Result<Self, RecordingError> {
        let compression = match compression {
            ChunkCompression::Zstd => Compression::Zstd,
            ChunkCompression::Lz4 => Compression::Lz4,
        };
        let options = WriteOptions::new()
            .compression(Some(compression))
            .compression_threads(0)
            .library(format!(
                "driftwatch/{} ({})",
                env!("CARGO_PKG_VERSION"),
                mcap::LIBRARY_IDENTIFIER
            ));
        let w =
            Positioned::new(w).map_err(|e| RecordingError::from_mcap_write(McapError::Io(e)))?;
        let inner = Writer::with_options(w, options).map_err(RecordingError::from_mcap_write)?;
        Ok(Self {
            inner,
            channels: HashMap::new(),
            held: None,
        })
    }

    /// Hold messages back and write them as one chunk at each [`Self::flush`], or once their
    /// payloads reach `limit` bytes, instead of streaming them into an open chunk: for
    /// writers kept open by the thousand, whose open chunk's compressor would outweigh the
    /// messages between flushes. The file holds the same messages in the same order; only
    /// where chunks end differs. What is held is lost in a crash, as an open chunk is.
    pub fn hold_up_to(mut self, limit: usize) -> Self {
        self.held = Some(Held {
            limit,
            messages: Vec::new(),
            topics: Vec::new(),
            data: Vec::new(),
        });
        self
    }

    /// Appends `msg` as JSON on `topic` with log and publish time `t_ns` (ns since the Unix
    /// epoch).
    pub fn write<T: Serialize + ?Sized>(
        &mut self,
        topic: &str,
        t_ns: i64,
        msg: &T,
    ) -> Result<(), RecordingError> {
        let data = serde_json::to_vec(msg).map_err(|e| RecordingError::Json {
            topic: topic.to_string(),
            detail: e.to_string(),
        })?;
        self.write_json_bytes(topic, t_ns, &data)
    }

    /// Appends an already encoded JSON payload (relayed or imported messages, test input).
    pub fn write_json_bytes(
        &mut self,
        topic: &str,
        t_ns: i64,
        data: &[u8],
    ) -> Result<(), RecordingError> {
        let Ok(time) = u64::try_from(t_ns) else {
            return Err(RecordingError::NegativeTime {
                topic: topic.to_string(),
                t_ns,
            });
        };
        if let Some(h) = &mut self.held {
            let index = h.topics.iter().position(|t| t == topic);
            let topic_at = u32::try_from(index.unwrap_or(h.topics.len()));
            if let (Ok(topic_at), Ok(end)) = (topic_at, u32::try_from(h.data.len() + data.len())) {
                if index.is_none() {
                    h.topics.push(topic.to_string());
                }
                h.data.extend_from_slice(data);
                h.messages.push(HeldMessage {
                    time,
                    topic: topic_at,
                    end,
                });
                if h.data.len() >= h.limit {
                    return self.flush();
                }
                return Ok(());
            }
            // Past what an index of a held message reaches (4 GiB held, or as many topics):
            // what is held goes first, then this one, so that the order stays.
            self.flush()?;
        }
        self.write_now(topic, time, data)
    }

    fn write_now(&mut self, topic: &str, time: u64, data: &[u8]) -> Result<(), RecordingError> {
        let channel = self.channel(topic)?;
        let sequence = channel.next_sequence;
        channel.next_sequence = sequence.wrapping_add(1);
        let header = MessageHeader {
            channel_id: channel.id,
            sequence,
            log_time: time,
            publish_time: time,
        };
        self.inner
            .write_to_known_channel(&header, data)
            .map_err(RecordingError::from_mcap_write)
    }

    fn channel(&mut self, topic: &str) -> Result<&mut ChannelState, RecordingError> {
        if !self.channels.contains_key(topic) {
            let (name, schema) = driftwatch_core::recording::schema(topic);
            let schema_id = self
                .inner
                .add_schema(&name, "jsonschema", schema.to_string().as_bytes())
                .map_err(RecordingError::from_mcap_write)?;
            let id = self
                .inner
                .add_channel(schema_id, topic, "json", &Default::default())
                .map_err(RecordingError::from_mcap_write)?;
            self.channels.insert(
                topic.to_string(),
                ChannelState {
                    id,
                    next_sequence: 0,
                },
            );
        }
        Ok(self
            .channels
            .get_mut(topic)
            .expect("the channel was registered above"))
    }

    /// Closes the current chunk and flushes the underlying writer, so a crash after this loses
    /// nothing written before it. (This hands the data to the OS; it does not fsync.) Held
    /// messages stay held until their chunk is closed: after a failure part way (a full
    /// disk), [`Self::take_held`] gives back every one of them.
    pub fn flush(&mut self) -> Result<(), RecordingError> {
        let held = self.held.take();
        let result = self
            .hand_over(held.as_ref())
            .and_then(|()| self.inner.flush().map_err(RecordingError::from_mcap_write));
        // Once written, the buffers are freed, not kept at their largest size.
        self.held = held.map(|h| if result.is_ok() { h.emptied() } else { h });
        result
    }

    /// Write `held`'s messages into the `mcap` writer's chunk.
    fn hand_over(&mut self, held: Option<&Held>) -> Result<(), RecordingError> {
        if let Some(h) = held {
            for (topic, time, payload) in h.each() {
                self.write_now(topic, time, payload)?;
            }
        }
        Ok(())
    }

    /// The messages held back and not yet in a closed chunk, oldest first; the writer holds
    /// none after. After a failed [`Self::flush`], these are the messages its file may lack.
    pub fn take_held(&mut self) -> Vec<driftwatch_core::recording::RawMessage> {
        let Some(h) = self.held.take() else {
            return Vec::new();
        };
        let out = h
            .each()
            .map(
                |(topic, time, payload)| driftwatch_core::recording::RawMessage {
                    topic: topic.to_string(),
                    // Held only from an i64 that was not negative.
                    t_ns: i64::try_from(time).unwrap_or(i64::MAX),
                    data: payload.to_vec(),
                },
            )
            .collect();
        self.held = Some(h.emptied());
        out
    }

    /// Closes the last chunk, writes the summary, footer and end magic, and returns the
    /// underlying writer.
    pub fn finish(mut self) -> Result<W, RecordingError> {
        if self.held.is_some() {
            self.flush()?;
        }
        self.inner
            .finish()
            .map_err(RecordingError::from_mcap_write)?;
        Ok(self.inner.into_inner().inner)
    }
}

/// A writer that knows its own position. The `mcap` writer asks for its position several
/// times a chunk (where the chunk starts, where its data start and end, where its rewritten
/// header ends); a [`std::io::BufWriter`] answers each by writing out its buffer and asking
/// the file (a write and an `lseek` per question). Here the position is counted from what
/// was written, and only a seek that moves goes to `inner`. The bytes written are the same.
struct Positioned<W> {
    inner: W,
    pos: u64,
}

impl<W: Seek> Positioned<W> {
    fn new(mut inner: W) -> std::io::Result<Self> {
        let pos = inner.stream_position()?;
        Ok(Positioned { inner, pos })
    }
}

impl<W: Write> Write for Positioned<W> {
    fn write(&mut self, buf: &[u8]) -> std::io::Result<usize> {
        let n = self.inner.write(buf)?;
        self.pos += n as u64;
        Ok(n)
    }

    fn flush(&mut self) -> std::io::Result<()> {
        self.inner.flush()
    }
}

impl<W: Seek> Seek for Positioned<W> {
    fn seek(&mut self, to: SeekFrom) -> std::io::Result<u64> {
        if to == SeekFrom::Current(0) {
            return Ok(self.pos);
        }
        self.pos = self.inner.seek(to)?;
        Ok(self.pos)
    }
}

impl RecordingWriter<BufWriter<File>> {
    /// Creates (or truncates) `path` and starts a recording in it.
    pub fn create_file(path: &Path) -> Result<Self, RecordingError> {
        Self::create_file_with(path, ChunkCompression::Zstd)
    }

    /// Creates (or truncates) `path` and starts a recording in it, its chunks compressed as
    /// `compression` says.
    pub fn create_file_with(
        path: &Path,
        compression: ChunkCompression,
    ) -> Result<Self, RecordingError> {
        let file = File::create(path).map_err(|error| RecordingError::Io {
            action: "create",
            path: Some(path.to_path_buf()),
            error,
        })?;
        Self::with_compression(BufWriter::with_capacity(FILE_BUFFER, file), compression)
            .map_err(|e| e.with_path(path))
    }
}

/// The file's write buffer, bytes. It gathers the small records (message indexes, a chunk's
/// header); a chunk's compressed data go past it in one write. A service keeps one file open
/// per machine all day, each with its buffer: std's default of 8 KiB, by the thousand, weighs
/// more than the few writes a smaller one adds.
const FILE_BUFFER: usize = 2048;

/// Writes a whole recording to `path`: `/machine/info` first, then every message of the
/// contract topics it holds in time order (detections that could not be parsed are left out).
pub fn write_recording_file(path: &Path, r: &Recording) -> Result<(), RecordingError> {
    let mut w = RecordingWriter::create_file(path)?;
    let mut items: Vec<(i64, &str, serde_json::Value)> = Vec::new();
    let mut push =
        |t: i64, topic: &'static str, v: Result<serde_json::Value, serde_json::Error>| {
            if let Ok(v) = v {
                items.push((t, topic, v));
            }
        };
    for m in &r.states {
        push(m.t_ns, TOPIC_STATE, serde_json::to_value(&m.msg));
    }
    for m in &r.spindle {
        push(m.t_ns, TOPIC_SPINDLE, serde_json::to_value(&m.msg));
    }
    for m in &r.temperatures {
        push(m.t_ns, TOPIC_TEMPERATURE, serde_json::to_value(&m.msg));
    }
    for m in &r.displacements {
        push(m.t_ns, TOPIC_DISPLACEMENT, serde_json::to_value(&m.msg));
    }
    for m in &r.detections {
        if let Ok(d) = &m.msg {
            push(m.t_ns, TOPIC_DETECTION, serde_json::to_value(d));
        }
    }
    for m in &r.results {
        push(m.t_ns, TOPIC_RESULT, serde_json::to_value(&m.msg));
    }
    items.sort_by_key(|i| i.0);
    let t0 = items.first().map_or(0, |i| i.0);
    if let Some(info) = &r.info {
        w.write(TOPIC_INFO, t0, info)
            .map_err(|e| e.with_path(path))?;
    }
    for (t, topic, v) in &items {
        w.write(topic, *t, v).map_err(|e| e.with_path(path))?;
    }
    w.finish().map_err(|e| e.with_path(path))?;
    Ok(())
}

/// Creates (or truncates) `path` and starts a recording in it; the same as
/// [`RecordingWriter::create_file`].
pub fn create_file(path: &Path) -> Result<RecordingWriter<BufWriter<File>>, RecordingError> {
    RecordingWriter::create_file(path)
}

// ------------------------------------------------------------------------------------------
// Reading
// ------------------------------------------------------------------------------------------

#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct ReadOptions {
    /// Read a file that ends early (or has damaged data) up to the first record that cannot be
    /// read, instead of failing. `Recording::truncated` then says what was lost.
    pub recover_truncated: bool,
    /// Also keep every message as it was written (topic, log time, bytes), in file order, in
    /// `Recording::raw`: for copying a file whole, topics this reader does not know included.
    pub keep_raw: bool,
}

/// Reads the recording in `path`. Errors name the file where they concern it as a whole.
pub fn read_file(path: &Path, opts: &ReadOptions) -> Result<Recording, RecordingError> {
    let bytes = std::fs::read(path).map_err(|error| RecordingError::Io {
        action: "read",
        path: Some(path.to_path_buf()),
        error,
    })?;
    read_recording(&bytes, opts).map_err(|e| e.with_path(path))
}

/// Reads a recording held in memory. Messages of each topic come out sorted by log time
/// (stable); unknown topics are counted, unparseable messages of known topics are skipped and
/// described in `Recording::problems`.
pub fn read_recording(bytes: &[u8], opts: &ReadOptions) -> Result<Recording, RecordingError> {
    let mut scan = Scan {
        bytes,
        channels: HashMap::new(),
        rec: Recording::default(),
        messages: 0,
        keep_raw: opts.keep_raw,
    };
    let outcome = match check_start_magic(bytes) {
        Ok(()) => scan.records(),
        Err(stop) => Err(stop),
    };
    match outcome {
        Ok(()) => {}
        Err(Stop::Fatal(e)) => return Err(e),
        Err(Stop::Truncated(detail)) if opts.recover_truncated => {
            scan.rec.truncated = Some(format!(
                "the recording ends early ({detail}); {} read from its complete chunks",
                count_messages(scan.messages)
            ));
        }
        Err(Stop::Truncated(detail)) => {
            return Err(RecordingError::Truncated {
                messages_read: scan.messages,
                detail,
            });
        }
        Err(Stop::Corrupt(detail)) if opts.recover_truncated => {
            scan.rec.truncated = Some(format!(
                "reading stopped at damaged data ({detail}); {} before it were read",
                count_messages(scan.messages)
            ));
        }
        Err(Stop::Corrupt(detail)) => return Err(RecordingError::Corrupt { detail }),
    }
    let mut rec = scan.rec;
    rec.states.sort_by_key(|m| m.t_ns);
    rec.spindle.sort_by_key(|m| m.t_ns);
    rec.temperatures.sort_by_key(|m| m.t_ns);
    rec.displacements.sort_by_key(|m| m.t_ns);
    rec.detections.sort_by_key(|m| m.t_ns);
    rec.results.sort_by_key(|m| m.t_ns);
    Ok(rec)
}

fn count_messages(n: u64) -> String {
    if n == 1 {
        "1 message was".to_string()
    } else {
        format!("{n} messages were")
    }
}

/// Why reading stopped before the end of the file.
enum Stop {
    /// The file ends inside a record, or before its footer.
    Truncated(String),
    /// A record cannot be read.
    Corrupt(String),
    /// The file cannot be taken at all, whatever the options.
    Fatal(RecordingError),
}

fn check_start_magic(bytes: &[u8]) -> Result<(), Stop> {
    let not_mcap = |detail: String| {
        Stop::Fatal(RecordingError::NotMcap {
            name: "the input".to_string(),
            detail,
        })
    };
    if bytes.is_empty() {
        return Err(not_mcap("it is empty".to_string()));
    }
    if bytes.starts_with(MAGIC) {
        return Ok(());
    }
    if MAGIC.starts_with(bytes) {
        return Err(Stop::Truncated(format!(
            "it is only {} bytes long and ends inside the MCAP magic",
            bytes.len()
        )));
    }
    let head = &bytes[..bytes.len().min(MAGIC.len())];
    let mut detail = format!("it starts with {} instead of the MCAP magic", hex(head));
    if head.get(1..5) == Some(b"MCAP".as_slice()) {
        let version = head
            .get(5)
            .map_or("?".to_string(), |v| format!("0x{v:02x}"));
        detail = format!("it is MCAP format version {version}; only version 0x30 is supported");
    } else if matches!(
        bytes.iter().find(|b| !b.is_ascii_whitespace()),
        Some(b'{' | b'[')
    ) {
        detail.push_str("; it looks like JSON text");
    }
    Err(not_mcap(detail))
}

fn hex(bytes: &[u8]) -> String {
    let mut s = String::new();
    for (i, b) in bytes.iter().enumerate() {
        if i > 0 {
            s.push(' ');
        }
        let _ = write!(s, "{b:02x}");
    }
    s
}

fn record_name(opcode: u8) -> String {
    match opcode {
        op::HEADER => "header".into(),
        op::FOOTER => "footer".into(),
        op::SCHEMA => "schema".into(),
        op::CHANNEL => "channel".into(),
        op::MESSAGE => "message".into(),
        op::CHUNK => "chunk".into(),
        op::MESSAGE_INDEX => "message index".into(),
        op::CHUNK_INDEX => "chunk index".into(),
        op::ATTACHMENT => "attachment".into(),
        op::ATTACHMENT_INDEX => "attachment index".into(),
        op::STATISTICS => "statistics".into(),
        op::METADATA => "metadata".into(),
        op::METADATA_INDEX => "metadata index".into(),
        op::SUMMARY_OFFSET => "summary offset".into(),
        op::DATA_END => "data end".into(),
        other => format!("opcode 0x{other:02x}"),
    }
}

/// Little-endian fields of one record body, bounds-checked.
struct Fields<'a> {
    data: &'a [u8],
    pos: usize,
}

impl<'a> Fields<'a> {
    fn new(data: &'a [u8]) -> Self {
        Self { data, pos: 0 }
    }

    fn take(&mut self, n: usize, what: &str) -> Result<&'a [u8], String> {
        if self.data.len() - self.pos < n {
            return Err(format!("its {what} runs past the end of the record"));
        }
        let s = &self.data[self.pos..self.pos + n];
        self.pos += n;
        Ok(s)
    }

    fn array<const N: usize>(&mut self, what: &str) -> Result<[u8; N], String> {
        let mut a = [0u8; N];
        a.copy_from_slice(self.take(N, what)?);
        Ok(a)
    }

    fn u16(&mut self, what: &str) -> Result<u16, String> {
        self.array(what).map(u16::from_le_bytes)
    }

    fn u32(&mut self, what: &str) -> Result<u32, String> {
        self.array(what).map(u32::from_le_bytes)
    }

    fn u64(&mut self, what: &str) -> Result<u64, String> {
        self.array(what).map(u64::from_le_bytes)
    }

    fn string(&mut self, what: &str) -> Result<&'a str, String> {
        let len = self.u32(what)? as usize;
        std::str::from_utf8(self.take(len, what)?).map_err(|_| format!("its {what} is not UTF-8"))
    }

    fn rest(&self) -> &'a [u8] {
        &self.data[self.pos..]
    }
}

struct ChannelDef {
    topic: String,
    encoding: String,
}

struct RawMessage<'a> {
    channel_id: u16,
    log_time: u64,
    data: &'a [u8],
}

fn parse_message(body: &[u8]) -> Result<RawMessage<'_>, String> {
    let mut f = Fields::new(body);
    let channel_id = f.u16("channel id")?;
    let _sequence = f.u32("sequence")?;
    let log_time = f.u64("log time")?;
    let _publish_time = f.u64("publish time")?;
    Ok(RawMessage {
        channel_id,
        log_time,
        data: f.rest(),
    })
}

struct Scan<'a> {
    keep_raw: bool,
    bytes: &'a [u8],
    channels: HashMap<u16, ChannelDef>,
    rec: Recording,
    /// Messages taken so far, of any topic.
    messages: u64,
}

impl Scan<'_> {
    /// Walks the top-level records after the start magic up to the footer and end magic.
    fn records(&mut self) -> Result<(), Stop> {
        let b = self.bytes;
        // A file that still ends with the magic was closed; a record running past its end is
        // damage, not truncation.
        let closed = b.len() >= 2 * MAGIC.len() && b.ends_with(MAGIC);
        let overrun = |detail: String| {
            if closed {
                Stop::Corrupt(detail)
            } else {
                Stop::Truncated(detail)
            }
        };
        let mut pos = MAGIC.len();
        let mut past_data_end = false;
        loop {
            let left = b.len() - pos;
            if left == 0 {
                return Err(overrun(format!(
                    "it stops after {pos} bytes without the footer that closes a finished recording"
                )));
            }
            if left < RECORD_PREFIX {
                return Err(overrun(format!(
                    "it ends {left} bytes into the record at byte {pos}"
                )));
            }
            let opcode = b[pos];
            let mut len_bytes = [0u8; 8];
            len_bytes.copy_from_slice(&b[pos + 1..pos + RECORD_PREFIX]);
            let len = u64::from_le_bytes(len_bytes);
            let body_start = pos + RECORD_PREFIX;
            let available = b.len() - body_start;
            if len > available as u64 {
                return Err(overrun(format!(
                    "the {} record at byte {pos} needs {len} bytes but only {available} follow",
                    record_name(opcode)
                )));
            }
            let next = body_start + len as usize;
            let body = &b[body_start..next];
            match opcode {
                op::FOOTER => {
                    let after = &b[next..];
                    return if after.starts_with(MAGIC) {
                        Ok(())
                    } else if MAGIC.starts_with(after) {
                        Err(Stop::Truncated(
                            "it ends inside the closing MCAP magic".to_string(),
                        ))
                    } else {
                        Err(Stop::Corrupt(format!(
                            "the footer at byte {pos} is not followed by the MCAP magic"
                        )))
                    };
                }
                op::DATA_END => past_data_end = true,
                // The summary section repeats schemas and channels and holds no messages.
                _ if past_data_end => {}
                op::CHANNEL => self.channel(body, &format!("at byte {pos}"))?,
                op::MESSAGE => {
                    let at = format!("at byte {pos}");
                    let m = parse_message(body)
                        .map_err(|e| Stop::Corrupt(format!("the message {at}: {e}")))?;
                    self.message(&m, &at)?;
                }
                op::CHUNK => self.chunk(body, pos)?,
                // Header, schemas (not needed to read JSON), indexes, attachments, metadata,
                // statistics and records of later format versions.
                _ => {}
            }
            pos = next;
        }
    }

    fn channel(&mut self, body: &[u8], at: &str) -> Result<(), Stop> {
        let parse = || -> Result<(u16, String, String), String> {
            let mut f = Fields::new(body);
            let id = f.u16("channel id")?;
            let _schema_id = f.u16("schema id")?;
            let topic = f.string("topic")?.to_string();
            let encoding = f.string("message encoding")?.to_string();
            Ok((id, topic, encoding))
        };
        let (id, topic, encoding) =
            parse().map_err(|e| Stop::Corrupt(format!("the channel record {at}: {e}")))?;
        if let Some(old) = self.channels.get(&id) {
            if old.topic != topic || old.encoding != encoding {
                return Err(Stop::Corrupt(format!(
                    "channel {id} is defined twice, as {} ({}) and {at} as {topic} ({encoding})",
                    old.topic, old.encoding
                )));
            }
            return Ok(());
        }
        self.channels.insert(id, ChannelDef { topic, encoding });
        Ok(())
    }

    /// Reads one complete chunk record: checks its CRC, then takes its channels and messages.
    fn chunk(&mut self, body: &[u8], offset: usize) -> Result<(), Stop> {
        let corrupt = |e: String| Stop::Corrupt(format!("the chunk at byte {offset}: {e}"));
        let mut f = Fields::new(body);
        let mut header = || -> Result<(u64, String, u64), String> {
            let _start = f.u64("start time")?;
            let _end = f.u64("end time")?;
            let uncompressed = f.u64("uncompressed size")?;
            let _crc = f.u32("CRC")?;
            let compression = f.string("compression name")?.to_string();
            let compressed = f.u64("compressed size")?;
            Ok((uncompressed, compression, compressed))
        };
        let (uncompressed, compression, compressed) = header().map_err(corrupt)?;
        let header_len = f.pos;
        if compressed > f.rest().len() as u64 {
            return Err(corrupt(format!(
                "it claims {compressed} compressed bytes but holds {}",
                f.rest().len()
            )));
        }
        if !matches!(compression.as_str(), "" | "zstd" | "lz4") {
            return Err(Stop::Fatal(RecordingError::Unsupported {
                detail: format!("chunk compression '{compression}' (chunk at byte {offset})"),
            }));
        }
        if uncompressed > MAX_CHUNK_BYTES {
            return Err(corrupt(format!(
                "it claims {uncompressed} bytes uncompressed, more than the {MAX_CHUNK_BYTES} this reader accepts"
            )));
        }
        if compression.is_empty() && uncompressed != compressed {
            return Err(corrupt(format!(
                "it is uncompressed but claims {compressed} bytes stored and {uncompressed} bytes of records"
            )));
        }
        // The chunk alone, without any padding after its records, for a fresh reader: its
        // records then cannot reach outside the chunk.
        let kept = header_len + compressed as usize;
        let mut record = Vec::with_capacity(RECORD_PREFIX + kept);
        record.push(op::CHUNK);
        record.extend_from_slice(&(kept as u64).to_le_bytes());
        record.extend_from_slice(&body[..kept]);
        let limit = uncompressed.max(compressed).max(kept as u64).max(64) as usize;
        let mut reader = LinearReader::new_with_options(
            LinearReaderOptions::default()
                .with_skip_start_magic(true)
                .with_skip_end_magic(true)
                .with_prevalidate_chunk_crcs(true)
                .with_record_length_limit(limit),
        );
        let at = format!("in the chunk at byte {offset}");
        let mut fed = false;
        let mut staged: Vec<(u16, u64, Vec<u8>)> = Vec::new();
        while let Some(event) = reader.next_event() {
            match event.map_err(|e| corrupt(e.to_string()))? {
                LinearReadEvent::ReadRequest(_) => {
                    if fed {
                        reader.notify_read(0);
                    } else {
                        reader.insert(record.len()).copy_from_slice(&record);
                        reader.notify_read(record.len());
                        fed = true;
                    }
                }
                LinearReadEvent::Record { opcode, data } => match opcode {
                    op::CHANNEL => self.channel(data, &at)?,
                    op::MESSAGE => {
                        let m = parse_message(data)
                            .map_err(|e| corrupt(format!("a message in it: {e}")))?;
                        staged.push((m.channel_id, m.log_time, m.data.to_vec()));
                    }
                    _ => {}
                },
            }
        }
        for (channel_id, log_time, data) in &staged {
            let m = RawMessage {
                channel_id: *channel_id,
                log_time: *log_time,
                data,
            };
            self.message(&m, &at)?;
        }
        Ok(())
    }

    fn message(&mut self, m: &RawMessage<'_>, at: &str) -> Result<(), Stop> {
        let Some(channel) = self.channels.get(&m.channel_id) else {
            return Err(Stop::Corrupt(format!(
                "a message {at} belongs to channel {}, which the file does not define before it",
                m.channel_id
            )));
        };
        let topic = channel.topic.as_str();
        let Ok(t_ns) = i64::try_from(m.log_time) else {
            return Err(Stop::Corrupt(format!(
                "a {topic} message {at} has log time {} ns, past what this reader handles (year 2262)",
                m.log_time
            )));
        };
        if self.keep_raw {
            self.rec.raw.push(driftwatch_core::recording::RawMessage {
                topic: topic.to_string(),
                t_ns,
                data: m.data.to_vec(),
            });
        }
        if !KNOWN_TOPICS.contains(&topic) {
            *self.rec.other_topics.entry(topic.to_string()).or_insert(0) += 1;
            self.messages += 1;
            return Ok(());
        }
        if channel.encoding != "json" {
            return Err(Stop::Fatal(RecordingError::Encoding {
                topic: topic.to_string(),
                encoding: channel.encoding.clone(),
            }));
        }
        self.messages += 1;
        let rec = &mut self.rec;
        let problems = &mut rec.problems;
        match topic {
            TOPIC_INFO => {
                if let Some(info) = parse_json::<MachineInfo>(topic, t_ns, m.data, problems)
                    && rec.info.is_none()
                {
                    rec.info = Some(info);
                }
            }
            TOPIC_STATE => push_json::<StateMsg>(&mut rec.states, topic, t_ns, m.data, problems),
            TOPIC_SPINDLE => {
                push_json::<SpindleMsg>(&mut rec.spindle, topic, t_ns, m.data, problems);
            }
            TOPIC_TEMPERATURE => {
                push_json::<TemperatureMsg>(&mut rec.temperatures, topic, t_ns, m.data, problems);
            }
            TOPIC_DISPLACEMENT => {
                push_json::<DisplacementMsg>(&mut rec.displacements, topic, t_ns, m.data, problems);
            }
            TOPIC_RESULT => {
                push_json::<CycleResultMsg>(&mut rec.results, topic, t_ns, m.data, problems);
            }
            TOPIC_DETECTION => rec.detections.push(Timed {
                t_ns,
                msg: driftwatch_core::recording::parse_detection(m.data),
            }),
            _ => unreachable!("KNOWN_TOPICS and this match list the same topics"),
        }
        Ok(())
    }
}

fn parse_json<T: serde::de::DeserializeOwned>(
    topic: &str,
    t_ns: i64,
    data: &[u8],
    problems: &mut Vec<String>,
) -> Option<T> {
    match serde_json::from_slice(data) {
        Ok(v) => Some(v),
        Err(e) => {
            problems.push(format!("{topic} message at {t_ns} ns skipped: {e}"));
            None
        }
    }
}

fn push_json<T: serde::de::DeserializeOwned>(
    out: &mut Vec<Timed<T>>,
    topic: &str,
    t_ns: i64,
    data: &[u8],
    problems: &mut Vec<String>,
) {
    if let Some(msg) = parse_json(topic, t_ns, data, problems) {
        out.push(Timed { t_ns, msg });
    }
}

#[cfg(test)]
mod tests {
    use std::cell::RefCell;
    use std::collections::BTreeMap;
    use std::io::{Cursor, SeekFrom};
    use std::rc::Rc;

    use proptest::prelude::*;
    use serde_json::json;

    use super::*;
    use driftwatch_core::measurement::Axis;
    use driftwatch_core::recording::{
        DetectionMsg, DetectionStatus, MachineStateKind, ResultStatus, TOPIC_COMPENSATION,
        TOPIC_TRUTH,
    };

    fn detection(cycle: i64, step: &str, status: Option<DetectionStatus>) -> DetectionMsg {
        DetectionMsg {
            cycle,
            step: step.to_string(),
            b_deg: -30.0,
            c_deg: 90.0,
            axis: Axis::Z,
            direction: -1,
            feed_mm_min: 100.0,
            spindle_rpm: 0.0,
            tool_id: "EM10".to_string(),
            x_mm: 0.25,
            y_mm: -100.0,
            z_mm: 70.001,
            status,
        }
    }

    fn result(cycle: i64, t_ns: i64) -> CycleResultMsg {
        CycleResultMsg {
            cycle,
            t_ns,
            status: ResultStatus::Rejected,
            reason: Some("too few detections".to_string()),
            errors: None,
            sigma: None,
            residual_rms_um: None,
            chi2: None,
            dof: None,
            n_detections: Some(3),
            nuisance: None,
            redundancy_um: None,
            chi2_point: None,
            geometry: None,
            notes: None,
        }
    }

    fn write_all(f: impl FnOnce(&mut RecordingWriter<Cursor<Vec<u8>>>)) -> Vec<u8> {
        let mut w = RecordingWriter::new(Cursor::new(Vec::new())).unwrap();
        f(&mut w);
        w.finish().unwrap().into_inner()
    }

    fn read(bytes: &[u8]) -> Result<Recording, RecordingError> {
        read_recording(bytes, &ReadOptions::default())
    }

    fn recover(bytes: &[u8]) -> Result<Recording, RecordingError> {
        read_recording(
            bytes,
            &ReadOptions {
                recover_truncated: true,
                ..Default::default()
            },
        )
    }

    /// The recorder's lz4 chunks read back as the zstd ones do, message for message.
    #[test]
    fn lz4_chunks_read_back_as_zstd_ones() {
        let write = |c: ChunkCompression| {
            let mut w = RecordingWriter::with_compression(Cursor::new(Vec::new()), c).unwrap();
            for i in 0..500 {
                let msg = TemperatureMsg {
                    sensor: format!("s{}", i % 4),
                    celsius: 20.0 + f64::from(i) * 1e-3,
                };
                w.write(TOPIC_TEMPERATURE, i64::from(i), &msg).unwrap();
            }
            w.write(TOPIC_DETECTION, 1_000, &detection(1, "B0C0/z", None))
                .unwrap();
            w.finish().unwrap().into_inner()
        };
        let (zstd, lz4) = (write(ChunkCompression::Zstd), write(ChunkCompression::Lz4));
        assert_ne!(zstd, lz4);
        assert!(lz4.windows(3).any(|w| w == b"lz4"), "the chunks say lz4");
        let (a, b) = (read(&zstd).unwrap(), read(&lz4).unwrap());
        assert_eq!(b.temperatures.len(), 500);
        assert_eq!(a.temperatures, b.temperatures);
        assert_eq!(a.detections.len(), 1);
        assert_eq!(
            a.detections[0].msg.as_ref().ok(),
            b.detections[0].msg.as_ref().ok()
        );
    }

    #[test]
    fn every_topic_round_trips_sorted_by_log_time() {
        let info = MachineInfo {
            machine_id: "M1".into(),
            kinematics: "table-table BC".into(),
            software: "driftwatch test".into(),
        };
        let cutting = StateMsg {
            state: MachineStateKind::Cutting,
            program: Some("O1234".into()),
        };
        let idle = StateMsg {
            state: MachineStateKind::Idle,
            program: None,
        };
        let ok = detection(1, "B0C0/z", None);
        let no_trip = detection(1, "B-30C90/x", Some(DetectionStatus::NoTrip));
        let mut accepted = result(1, 5_000);
        accepted.status = ResultStatus::Ok;
        accepted.reason = None;
        accepted.errors = Some(BTreeMap::from([("EXB".to_string(), 1.5e-3)]));
        accepted.sigma = Some(BTreeMap::from([("EXB".to_string(), 2e-4)]));
        accepted.residual_rms_um = Some(0.4);
        accepted.redundancy_um = Some(vec![0.1, -0.2]);
        let rejected = result(2, 9_000);
        let bytes = write_all(|w| {
            w.write(TOPIC_INFO, 1, &info).unwrap();
            // Written out of order: readers sort each topic by log time.
            w.write(TOPIC_STATE, 20, &idle).unwrap();
            w.write(TOPIC_STATE, 10, &cutting).unwrap();
            w.write(TOPIC_SPINDLE, 11, &SpindleMsg { rpm: 12_000.0 })
                .unwrap();
            w.write(
                TOPIC_TEMPERATURE,
                12,
                &TemperatureMsg {
                    sensor: "spindle".into(),
                    celsius: 31.25,
                },
            )
            .unwrap();
            w.write(
                TOPIC_DISPLACEMENT,
                13,
                &DisplacementMsg {
                    sensor: "z".into(),
                    um: -4.5,
                },
            )
            .unwrap();
            w.write(TOPIC_DETECTION, 3_000, &no_trip).unwrap();
            w.write(TOPIC_DETECTION, 2_000, &ok).unwrap();
            w.write(TOPIC_RESULT, 9_000, &rejected).unwrap();
            w.write(TOPIC_RESULT, 5_000, &accepted).unwrap();
            w.write(TOPIC_TRUTH, 14, &json!({"eyb": 1e-3})).unwrap();
            w.write(TOPIC_TRUTH, 15, &json!({"eyb": 2e-3})).unwrap();
            w.write(TOPIC_COMPENSATION, 16, &json!({"EXB": 0.0}))
                .unwrap();
            w.write("/vendor/extra", 17, &json!([1, 2])).unwrap();
        });
        let r = read(&bytes).unwrap();
        assert_eq!(r.info, Some(info));
        assert_eq!(
            r.states,
            vec![
                Timed {
                    t_ns: 10,
                    msg: cutting
                },
                Timed {
                    t_ns: 20,
                    msg: idle
                }
            ]
        );
        assert_eq!(r.spindle[0].msg.rpm, 12_000.0);
        assert_eq!(r.temperatures[0].msg.celsius, 31.25);
        assert_eq!(r.displacements[0].t_ns, 13);
        assert_eq!(
            r.detections,
            vec![
                Timed {
                    t_ns: 2_000,
                    msg: Ok(ok)
                },
                Timed {
                    t_ns: 3_000,
                    msg: Ok(no_trip.clone())
                }
            ]
        );
        assert_eq!(
            r.detections[1].msg.as_ref().unwrap().status(),
            DetectionStatus::NoTrip
        );
        assert_eq!(
            r.results,
            vec![
                Timed {
                    t_ns: 5_000,
                    msg: accepted
                },
                Timed {
                    t_ns: 9_000,
                    msg: rejected
                }
            ]
        );
        assert_eq!(
            r.other_topics,
            BTreeMap::from([
                (TOPIC_COMPENSATION.to_string(), 1),
                ("/vendor/extra".to_string(), 1),
                (TOPIC_TRUTH.to_string(), 2),
            ])
        );
        assert!(r.problems.is_empty(), "{:?}", r.problems);
        assert_eq!(r.truncated, None);
    }

    #[test]
    fn the_file_follows_the_contract_layout() {
        let bytes = write_all(|w| {
            w.write(TOPIC_SPINDLE, 5, &SpindleMsg { rpm: 1.0 }).unwrap();
            w.write(TOPIC_SPINDLE, 6, &SpindleMsg { rpm: 2.0 }).unwrap();
        });
        let summary = mcap::Summary::read(&bytes).unwrap().expect("a summary");
        assert!(!summary.chunk_indexes.is_empty());
        assert!(
            summary
                .chunk_indexes
                .iter()
                .all(|c| c.compression == "zstd")
        );
        assert!(
            summary
                .chunk_indexes
                .iter()
                .all(|c| !c.message_index_offsets.is_empty())
        );
        let channel = summary.channels.values().next().unwrap();
        assert_eq!(channel.topic, TOPIC_SPINDLE);
        assert_eq!(channel.message_encoding, "json");
        let schema = channel.schema.as_ref().unwrap();
        assert_eq!(schema.encoding, "jsonschema");
        let doc: serde_json::Value = serde_json::from_slice(&schema.data).unwrap();
        assert_eq!(doc, driftwatch_core::recording::schema(TOPIC_SPINDLE).1);
        let messages: Vec<_> = mcap::MessageStream::new(&bytes)
            .unwrap()
            .collect::<Result<_, _>>()
            .unwrap();
        assert_eq!(messages[1].log_time, 6);
        assert_eq!(messages[1].publish_time, 6);
        assert_eq!(messages[1].sequence, 1);
    }

    #[test]
    fn unparseable_messages_of_known_topics_are_skipped_and_described() {
        let bytes = write_all(|w| {
            w.write(TOPIC_SPINDLE, 7, &json!({"rpm": "fast"})).unwrap();
            w.write(TOPIC_SPINDLE, 8, &json!({"rpm": 3.0, "new_field": true}))
                .unwrap();
            w.write(TOPIC_DETECTION, 9, &json!({"cycle": 4})).unwrap();
        });
        let r = read(&bytes).unwrap();
        assert_eq!(r.spindle.len(), 1);
        assert_eq!(r.problems.len(), 1);
        assert!(
            r.problems[0].contains("/spindle") && r.problems[0].contains("7 ns"),
            "{}",
            r.problems[0]
        );
        let issue = r.detections[0].msg.as_ref().unwrap_err();
        assert_eq!(issue.cycle, Some(4));
    }

    #[test]
    fn negative_times_are_refused() {
        let mut w = RecordingWriter::new(Cursor::new(Vec::new())).unwrap();
        let e = w
            .write(TOPIC_SPINDLE, -1, &SpindleMsg { rpm: 0.0 })
            .unwrap_err();
        assert!(matches!(e, RecordingError::NegativeTime { t_ns: -1, .. }));
        assert!(e.to_string().contains("/spindle"), "{e}");
    }

    fn many_detections(n: usize) -> Vec<DetectionMsg> {
        (0..n)
            .map(|i| detection(i as i64 / 10, &format!("step-{i}"), None))
            .collect()
    }

    #[test]
    fn a_cut_file_is_read_only_on_request_and_up_to_its_last_complete_chunk() {
        let written = many_detections(300);
        let bytes = write_all(|w| {
            for (i, d) in written.iter().enumerate() {
                w.write(TOPIC_DETECTION, 1_000 + i as i64, d).unwrap();
                if i % 10 == 9 {
                    w.flush().unwrap();
                }
            }
        });
        assert_eq!(read(&bytes).unwrap().detections.len(), written.len());
        let cut = &bytes[..bytes.len() * 2 / 3];

        let e = read(cut).unwrap_err();
        let RecordingError::Truncated { messages_read, .. } = &e else {
            panic!("expected Truncated, got {e:?}");
        };
        let messages_read = *messages_read as usize;
        assert!(e.to_string().contains("--recover"), "{e}");
        assert!(e.to_string().contains("ends early"), "{e}");

        let r = recover(cut).unwrap();
        let got = r.detections.len();
        assert!(got > 0 && got < written.len(), "{got}");
        assert_eq!(got, messages_read);
        assert_eq!(got % 10, 0, "whole chunks of 10 only");
        for (i, d) in r.detections.iter().enumerate() {
            assert_eq!(d.msg.as_ref().unwrap(), &written[i]);
        }
        assert!(r.truncated.as_deref().unwrap().contains("ends early"));

        // Every cut point is readable with recovery, and never yields a partial chunk.
        for len in (0..bytes.len()).step_by(97) {
            match recover(&bytes[..len]) {
                Ok(r) => assert_eq!(r.detections.len() % 10, 0),
                Err(e) => assert!(len == 0 && matches!(e, RecordingError::NotMcap { .. })),
            }
        }
    }

    /// An in-memory file that a test can look at while the writer still owns it.
    #[derive(Clone, Default)]
    struct SharedFile(Rc<RefCell<Cursor<Vec<u8>>>>);

    impl Write for SharedFile {
        fn write(&mut self, buf: &[u8]) -> std::io::Result<usize> {
            self.0.borrow_mut().write(buf)
        }
        fn flush(&mut self) -> std::io::Result<()> {
            Ok(())
        }
    }

    impl Seek for SharedFile {
        fn seek(&mut self, pos: SeekFrom) -> std::io::Result<u64> {
            self.0.borrow_mut().seek(pos)
        }
    }

    #[test]
    fn a_crashed_writer_leaves_everything_before_its_last_flush() {
        let file = SharedFile::default();
        let mut w = RecordingWriter::new(file.clone()).unwrap();
        let written = many_detections(45);
        for (i, d) in written.iter().enumerate() {
            w.write(TOPIC_DETECTION, i as i64, d).unwrap();
            if i == 29 {
                w.flush().unwrap();
            }
        }
        // The power fails now: the open chunk still has its placeholder header.
        let on_disk = file.0.borrow().get_ref().clone();
        drop(w);

        let e = read(&on_disk).unwrap_err();
        assert!(
            matches!(
                e,
                RecordingError::Truncated {
                    messages_read: 30,
                    ..
                }
            ),
            "{e:?}"
        );
        let r = recover(&on_disk).unwrap();
        let got: Vec<_> = r
            .detections
            .iter()
            .map(|d| d.msg.clone().unwrap())
            .collect();
        assert_eq!(got, written[..30]);
    }

    /// A file that counts the seeks that reach it.
    #[derive(Default)]
    struct SeekCounting {
        file: Cursor<Vec<u8>>,
        seeks: usize,
    }

    impl Write for SeekCounting {
        fn write(&mut self, buf: &[u8]) -> std::io::Result<usize> {
            self.file.write(buf)
        }
        fn flush(&mut self) -> std::io::Result<()> {
            Ok(())
        }
    }

    impl Seek for SeekCounting {
        fn seek(&mut self, pos: SeekFrom) -> std::io::Result<u64> {
            self.seeks += 1;
            self.file.seek(pos)
        }
    }

    /// The writer's own count of its position agrees with the file's through writes and
    /// seeks of every kind, and only the seeks that move reach the file (and one question at
    /// the start, where the file is).
    #[test]
    fn a_positioned_writer_counts_what_the_file_would_say() {
        let mut w = Positioned::new(SeekCounting::default()).unwrap();
        let moves = [
            SeekFrom::Start(3),
            SeekFrom::End(0),
            SeekFrom::Current(-2),
            SeekFrom::End(-5),
        ];
        for (i, to) in moves.into_iter().enumerate() {
            w.write_all(&vec![i as u8; 7 + i]).unwrap();
            assert_eq!(w.stream_position().unwrap(), w.inner.file.position());
            w.seek(to).unwrap();
            assert_eq!(w.stream_position().unwrap(), w.inner.file.position());
        }
        // The one question at the start, then the moves.
        assert_eq!(w.inner.seeks, 1 + moves.len());
    }

    /// A chunk's header is rewritten once its size is known: per chunk, one seek back to it
    /// and one to the end reach the file, and none to ask where the writer is (but the one at
    /// the start). Through a buffered file each of those questions was a write and an `lseek`.
    #[test]
    fn a_writer_seeks_its_file_only_to_rewrite_each_chunks_header() {
        let mut w =
            RecordingWriter::with_compression(SeekCounting::default(), ChunkCompression::Lz4)
                .unwrap()
                .hold_up_to(1 << 20);
        let written = many_detections(30);
        for (i, d) in written.iter().enumerate() {
            w.write(TOPIC_DETECTION, i as i64, d).unwrap();
            if i % 10 == 9 {
                w.flush().unwrap();
            }
        }
        let f = w.finish().unwrap();
        // Where the file starts, then two a chunk.
        assert_eq!(f.seeks, 1 + 2 * 3);
        let r = read(f.file.get_ref()).unwrap();
        assert_eq!(r.detections.len(), 30);
    }

    /// A file with `room` bytes left: a write past it fails as a full disk does.
    #[derive(Clone)]
    struct FullingFile {
        file: SharedFile,
        room: Rc<RefCell<usize>>,
    }

    impl Write for FullingFile {
        fn write(&mut self, buf: &[u8]) -> std::io::Result<usize> {
            let mut room = self.room.borrow_mut();
            if buf.len() > *room {
                return Err(std::io::ErrorKind::StorageFull.into());
            }
            *room -= buf.len();
            self.file.write(buf)
        }
        fn flush(&mut self) -> std::io::Result<()> {
            Ok(())
        }
    }

    impl Seek for FullingFile {
        fn seek(&mut self, pos: SeekFrom) -> std::io::Result<u64> {
            self.file.seek(pos)
        }
    }

    /// A flush that fails part way (the disk full in the middle of the chunk) leaves every
    /// held message to `take_held`, in order, for the caller to write elsewhere; one that
    /// succeeds leaves none. So does a failure of the flush the limit sets off.
    #[test]
    fn a_failed_flush_gives_back_every_held_message() {
        let written = many_detections(12);
        let raw = |i: usize| driftwatch_core::recording::RawMessage {
            topic: TOPIC_DETECTION.to_string(),
            t_ns: i as i64,
            data: serde_json::to_vec(&written[i]).unwrap(),
        };
        let one = raw(0).data.len();
        let room = Rc::new(RefCell::new(usize::MAX));
        let file = FullingFile {
            file: SharedFile::default(),
            room: room.clone(),
        };
        let mut w = RecordingWriter::with_compression(file, ChunkCompression::Lz4)
            .unwrap()
            .hold_up_to(4 * one);
        for (i, d) in written[..3].iter().enumerate() {
            w.write(TOPIC_DETECTION, i as i64, d).unwrap();
        }
        w.flush().unwrap();
        assert!(
            w.take_held().is_empty(),
            "a chunk written holds nothing back"
        );
        for (i, d) in written.iter().enumerate().take(6).skip(3) {
            w.write(TOPIC_DETECTION, i as i64, d).unwrap();
        }
        // Room for the chunk's header but not for its data.
        *room.borrow_mut() = 100;
        assert!(w.flush().is_err());
        assert_eq!(w.take_held(), (3..6).map(raw).collect::<Vec<_>>());
        assert!(w.take_held().is_empty(), "taken once");
        // The limit's flush fails at the fourth message: all four come back.
        let mut w = RecordingWriter::with_compression(
            FullingFile {
                file: SharedFile::default(),
                // Room for the file's header, not for a chunk.
                room: Rc::new(RefCell::new(150)),
            },
            ChunkCompression::Lz4,
        )
        .unwrap()
        .hold_up_to(4 * one);
        let results: Vec<bool> = (6..10)
            .map(|i| w.write(TOPIC_DETECTION, i as i64, &written[i]).is_ok())
            .collect();
        assert_eq!(results, [true, true, true, false]);
        assert_eq!(w.take_held(), (6..10).map(raw).collect::<Vec<_>>());
    }

    /// A writer that holds its messages back writes the same messages, in the same order, as
    /// one that streams them; nothing reaches the file between its flushes until the limit,
    /// and a crash then loses only what it held.
    #[test]
    fn a_writer_holding_its_messages_writes_them_at_each_flush_and_at_its_limit() {
        let written = many_detections(45);
        let streamed = write_all(|w| {
            for (i, d) in written.iter().enumerate() {
                w.write(TOPIC_DETECTION, i as i64, d).unwrap();
            }
        });
        let file = SharedFile::default();
        let size = || file.0.borrow().get_ref().len();
        let one = serde_json::to_vec(&written[0]).unwrap().len();
        let mut w = RecordingWriter::with_compression(file.clone(), ChunkCompression::Lz4)
            .unwrap()
            .hold_up_to(10 * one);
        let empty = size();
        for (i, d) in written[..5].iter().enumerate() {
            w.write(TOPIC_DETECTION, i as i64, d).unwrap();
        }
        assert_eq!(size(), empty, "held: nothing written before the flush");
        w.flush().unwrap();
        assert!(size() > empty, "the flush writes the held messages");
        let flushed = size();
        // The limit: about ten more messages hand themselves over without a flush.
        for (i, d) in written.iter().enumerate().take(20).skip(5) {
            w.write(TOPIC_DETECTION, i as i64, d).unwrap();
        }
        assert!(size() > flushed, "the limit wrote a chunk");
        let crashed = file.0.borrow().get_ref().clone();
        for (i, d) in written.iter().enumerate().skip(20) {
            w.write(TOPIC_DETECTION, i as i64, d).unwrap();
        }
        let held = w.finish().unwrap().0.borrow().get_ref().clone();

        let (a, b) = (read(&streamed).unwrap(), read(&held).unwrap());
        let msgs = |r: &Recording| -> Vec<_> {
            r.detections
                .iter()
                .map(|d| (d.t_ns, d.msg.clone().unwrap()))
                .collect()
        };
        assert_eq!(msgs(&a), msgs(&b), "the same messages in the same order");
        assert_eq!(b.detections.len(), 45);
        // What reached the file before the crash is every message up to the last hand-over.
        let r = recover(&crashed).unwrap();
        assert!(
            (10..20).contains(&r.detections.len()),
            "{}",
            r.detections.len()
        );
        assert_eq!(msgs(&r)[..], msgs(&b)[..r.detections.len()]);
    }

    #[test]
    fn garbage_is_not_an_mcap_file() {
        for bytes in [
            &b""[..],
            b"hello",
            b"this is certainly not a recording",
            b"{\"cycle\": 1}",
            &[0u8; 64],
            &[0x89, b'M', b'C', b'A', b'P', 0x31, b'\r', b'\n', 0, 0],
        ] {
            for opts in [
                ReadOptions::default(),
                ReadOptions {
                    recover_truncated: true,
                    ..Default::default()
                },
            ] {
                let e = read_recording(bytes, &opts).unwrap_err();
                assert!(matches!(e, RecordingError::NotMcap { .. }), "{e:?}");
                assert!(e.to_string().contains("is not an MCAP file"), "{e}");
            }
        }
        let e = read(b"[1, 2]").unwrap_err();
        assert!(e.to_string().contains("JSON"), "{e}");
        let e = read(&MAGIC[..5]).unwrap_err();
        assert!(
            matches!(
                e,
                RecordingError::Truncated {
                    messages_read: 0,
                    ..
                }
            ),
            "{e:?}"
        );

        // The magic followed by garbage is cut short or damaged, and never a panic.
        let mut bytes = MAGIC.to_vec();
        bytes.extend((0..200u32).map(|i| (i.wrapping_mul(2_654_435_761) >> 13) as u8));
        assert!(read(&bytes).is_err());
        bytes.extend_from_slice(MAGIC);
        let e = read(&bytes).unwrap_err();
        assert!(matches!(e, RecordingError::Corrupt { .. }), "{e:?}");
    }

    #[test]
    fn files_with_a_bad_footer_or_damaged_chunk_are_corrupt() {
        let bytes = write_all(|w| {
            for (i, d) in many_detections(30).iter().enumerate() {
                w.write(TOPIC_DETECTION, i as i64, d).unwrap();
            }
        });
        let mut bad_end = bytes.clone();
        let n = bad_end.len();
        bad_end[n - 1] ^= 0xff;
        assert!(matches!(
            read(&bad_end).unwrap_err(),
            RecordingError::Corrupt { .. }
        ));
        // A flipped byte in the compressed data of the first chunk fails its CRC (or its
        // decompression).
        let chunk = find_record(&bytes, op::CHUNK).unwrap();
        let mut flipped = bytes.clone();
        flipped[chunk + 120] ^= 0x55;
        let e = read(&flipped).unwrap_err();
        assert!(matches!(e, RecordingError::Corrupt { .. }), "{e:?}");
        assert!(e.to_string().contains("chunk at byte"), "{e}");
        let r = recover(&flipped).unwrap();
        assert!(r.detections.is_empty());
        assert!(r.truncated.unwrap().contains("damaged"));
    }

    /// Offset of the first top-level record with `opcode`.
    fn find_record(bytes: &[u8], opcode: u8) -> Option<usize> {
        let mut pos = MAGIC.len();
        while pos + RECORD_PREFIX <= bytes.len() {
            if bytes[pos] == opcode {
                return Some(pos);
            }
            let len = u64::from_le_bytes(bytes[pos + 1..pos + 9].try_into().unwrap());
            pos += RECORD_PREFIX + len as usize;
        }
        None
    }

    #[test]
    fn files_of_other_writers_are_accepted() {
        let configs = [
            (
                "lz4 chunks",
                WriteOptions::new().compression(Some(Compression::Lz4)),
            ),
            ("unchunked", WriteOptions::new().use_chunks(false)),
            ("uncompressed chunks", WriteOptions::new().compression(None)),
            (
                "no summary, no indexes",
                WriteOptions::new()
                    .compression(Some(Compression::Lz4))
                    .emit_summary_records(false)
                    .emit_summary_offsets(false)
                    .emit_message_indexes(false),
            ),
        ];
        for (name, options) in configs {
            let mut w = options.create(Cursor::new(Vec::new())).unwrap();
            // Schemaless json channel (schema id 0), as some writers make them.
            let spindle = w
                .add_channel(0, TOPIC_SPINDLE, "json", &BTreeMap::new())
                .unwrap();
            let (schema_name, schema) = driftwatch_core::recording::schema(TOPIC_STATE);
            let schema_id = w
                .add_schema(&schema_name, "jsonschema", schema.to_string().as_bytes())
                .unwrap();
            let state = w
                .add_channel(schema_id, TOPIC_STATE, "json", &BTreeMap::new())
                .unwrap();
            let other = w
                .add_channel(0, "/camera", "cdr", &BTreeMap::new())
                .unwrap();
            let mut put = |channel_id, t: u64, data: &[u8]| {
                let header = MessageHeader {
                    channel_id,
                    sequence: 0,
                    log_time: t,
                    publish_time: t,
                };
                w.write_to_known_channel(&header, data).unwrap();
            };
            put(spindle, 30, br#"{"rpm": 300.0, "unit": "1/min"}"#);
            put(state, 5, br#"{"state": "cutting", "program": null}"#);
            put(spindle, 10, br#"{"rpm": 100.0}"#);
            put(other, 1, &[0, 1, 2, 3]);
            put(spindle, 20, br#"{"rpm": NaN}"#);
            w.finish().unwrap();
            let bytes = w.into_inner().into_inner();

            let r = read(&bytes).unwrap_or_else(|e| panic!("{name}: {e}"));
            let rpm: Vec<_> = r.spindle.iter().map(|m| (m.t_ns, m.msg.rpm)).collect();
            assert_eq!(rpm, [(10, 100.0), (30, 300.0)], "{name}");
            assert_eq!(r.states[0].msg.state, MachineStateKind::Cutting, "{name}");
            assert_eq!(r.other_topics.get("/camera"), Some(&1), "{name}");
            assert_eq!(r.problems.len(), 1, "{name}: {:?}", r.problems);
            assert!(
                r.problems[0].contains("/spindle message at 20 ns"),
                "{name}"
            );
        }
    }

    #[test]
    fn a_non_json_channel_on_a_contract_topic_is_refused() {
        let mut w = mcap::Writer::new(Cursor::new(Vec::new())).unwrap();
        let schema_id = w
            .add_schema("ProbeDetection", "protobuf", b"\x0a\x00")
            .unwrap();
        let channel = w
            .add_channel(schema_id, TOPIC_DETECTION, "protobuf", &BTreeMap::new())
            .unwrap();
        let header = MessageHeader {
            channel_id: channel,
            sequence: 0,
            log_time: 1,
            publish_time: 1,
        };
        w.write_to_known_channel(&header, &[8, 1]).unwrap();
        w.finish().unwrap();
        let bytes = w.into_inner().into_inner();
        for opts in [
            ReadOptions::default(),
            ReadOptions {
                recover_truncated: true,
                ..Default::default()
            },
        ] {
            let e = read_recording(&bytes, &opts).unwrap_err();
            let RecordingError::Encoding { topic, encoding } = &e else {
                panic!("expected Encoding, got {e:?}");
            };
            assert_eq!(
                (topic.as_str(), encoding.as_str()),
                (TOPIC_DETECTION, "protobuf")
            );
            assert!(e.to_string().contains("/probe/detection"), "{e}");
        }
    }

    /// Inputs that panic inside `mcap` 0.26's own readers (slice and overflow panics on
    /// hostile lengths). This reader reports them as errors.
    #[test]
    fn hostile_lengths_are_errors() {
        let mut attachment = MAGIC.to_vec();
        let body = [0u8; 32];
        attachment.push(op::ATTACHMENT);
        attachment.extend_from_slice(&(body.len() as u64).to_le_bytes());
        attachment.extend_from_slice(&body);
        assert!(matches!(
            read(&attachment).unwrap_err(),
            RecordingError::Truncated { .. }
        ));
        let mut huge = MAGIC.to_vec();
        huge.push(op::MESSAGE);
        huge.extend_from_slice(&(u64::MAX - 3).to_le_bytes());
        huge.extend_from_slice(&[0u8; 20]);
        assert!(read(&huge).is_err());

        // Uncompressed chunks whose inner record claims to be enormous, or to reach past the
        // chunk into the padding after it.
        for inner_len in [u64::MAX - 3, 40] {
            let file = file_with_bad_chunk(inner_len);
            let e = read(&file).unwrap_err();
            assert!(matches!(e, RecordingError::Corrupt { .. }), "{e:?}");
            let e = read(&file[..file.len() - 50]).unwrap_err();
            assert!(matches!(e, RecordingError::Corrupt { .. }), "{e:?}");
        }
    }

    fn file_with_bad_chunk(inner_len: u64) -> Vec<u8> {
        let mut inner = vec![op::MESSAGE];
        inner.extend_from_slice(&inner_len.to_le_bytes());
        inner.extend_from_slice(&[0u8; 8]);
        let mut chunk = Vec::new();
        for v in [0u64, 0, inner.len() as u64] {
            chunk.extend_from_slice(&v.to_le_bytes());
        }
        chunk.extend_from_slice(&0u32.to_le_bytes()); // CRC 0: not checked
        chunk.extend_from_slice(&0u32.to_le_bytes()); // compression ""
        chunk.extend_from_slice(&(inner.len() as u64).to_le_bytes());
        chunk.extend_from_slice(&inner);
        chunk.extend_from_slice(&[0u8; 64]); // padding the record may not reach into
        let mut file = MAGIC.to_vec();
        file.push(op::CHUNK);
        file.extend_from_slice(&(chunk.len() as u64).to_le_bytes());
        file.extend_from_slice(&chunk);
        file.push(op::DATA_END);
        file.extend_from_slice(&4u64.to_le_bytes());
        file.extend_from_slice(&[0u8; 4]);
        file.push(op::FOOTER);
        file.extend_from_slice(&20u64.to_le_bytes());
        file.extend_from_slice(&[0u8; 20]);
        file.extend_from_slice(MAGIC);
        file
    }

    #[test]
    fn io_errors_name_the_path() {
        let path = Path::new("/nonexistent-dir/driftwatch/rec.mcap");
        let e = read_file(path, &ReadOptions::default()).unwrap_err();
        assert!(
            e.to_string()
                .contains("/nonexistent-dir/driftwatch/rec.mcap"),
            "{e}"
        );
        let Err(e) = create_file(path) else {
            panic!("created a file in a missing directory");
        };
        assert!(
            e.to_string().contains("cannot create /nonexistent-dir"),
            "{e}"
        );
    }

    #[test]
    fn files_round_trip_through_the_file_system() {
        let dir = std::env::temp_dir().join(format!("driftwatch-mcap-io-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let path = dir.join("rec.mcap");
        let mut w = create_file(&path).unwrap();
        w.write(TOPIC_SPINDLE, 1, &SpindleMsg { rpm: 5.0 }).unwrap();
        w.finish().unwrap();
        let r = read_file(&path, &ReadOptions::default()).unwrap();
        assert_eq!(r.spindle.len(), 1);
        std::fs::write(&path, b"not mcap").unwrap();
        let e = read_file(&path, &ReadOptions::default()).unwrap_err();
        assert!(
            e.to_string().starts_with(&path.display().to_string()),
            "{e}"
        );
        std::fs::remove_dir_all(&dir).unwrap();
    }

    /// Whether this build's serde_json parses every float back to the same bits (its
    /// `float_roundtrip` feature); without it, about 30% of arbitrary floats (10% of floats of
    /// instrument-like magnitude) come back 1 or 2 ULP off.
    fn json_floats_round_trip_exactly() -> bool {
        let x = 0.976_706_226_043_416_7_f64;
        serde_json::from_str::<f64>(&serde_json::to_string(&x).unwrap()).unwrap() == x
    }

    fn ulps_apart(a: f64, b: f64) -> u64 {
        let key = |x: f64| {
            let bits = x.to_bits() as i64;
            if bits < 0 { i64::MIN - bits } else { bits }
        };
        key(a).abs_diff(key(b))
    }

    fn same_detection(a: &DetectionMsg, b: &DetectionMsg, exact: bool) -> bool {
        let floats = |m: &DetectionMsg| {
            [
                m.b_deg,
                m.c_deg,
                m.feed_mm_min,
                m.spindle_rpm,
                m.x_mm,
                m.y_mm,
                m.z_mm,
            ]
        };
        let close = floats(a).iter().zip(floats(b)).all(|(x, y)| {
            if exact {
                *x == y
            } else {
                ulps_apart(*x, y) <= 4
            }
        });
        close
            && (a.cycle, &a.step, a.axis, a.direction, &a.tool_id, a.status)
                == (b.cycle, &b.step, b.axis, b.direction, &b.tool_id, b.status)
    }

    fn finite_f64() -> impl Strategy<Value = f64> {
        use proptest::num::f64 as f;
        prop_oneof![
            // Decimal values as instruments report them: always exact.
            (-10_000_000_000i64..10_000_000_000, 0i32..7)
                .prop_map(|(m, k)| m as f64 / 10f64.powi(k)),
            f::POSITIVE | f::NEGATIVE | f::NORMAL | f::SUBNORMAL | f::ZERO,
        ]
    }

    fn detection_msg() -> impl Strategy<Value = DetectionMsg> {
        let axis = prop_oneof![Just(Axis::X), Just(Axis::Y), Just(Axis::Z)];
        let status = prop_oneof![
            Just(None),
            Just(Some(DetectionStatus::Ok)),
            Just(Some(DetectionStatus::NoTrip)),
            Just(Some(DetectionStatus::Aborted)),
        ];
        (
            (
                -1_000i64..1_000_000_000,
                ".*",
                ".*",
                axis,
                prop_oneof![Just(-1i8), Just(1i8)],
            ),
            proptest::collection::vec(finite_f64(), 7),
            status,
        )
            .prop_map(|((cycle, step, tool_id, axis, direction), f, status)| {
                DetectionMsg {
                    cycle,
                    step,
                    b_deg: f[0],
                    c_deg: f[1],
                    axis,
                    direction,
                    feed_mm_min: f[2],
                    spindle_rpm: f[3],
                    tool_id,
                    x_mm: f[4],
                    y_mm: f[5],
                    z_mm: f[6],
                    status,
                }
            })
    }

    fn decimal(x: f64) -> bool {
        let s = serde_json::to_string(&x).unwrap();
        s.bytes().filter(u8::is_ascii_digit).count() <= 15 && x.abs() < 1e15 && x.abs() > 1e-7
            || x == 0.0
    }

    proptest::proptest! {
        #[test]
        fn arbitrary_bytes_never_panic(bytes in proptest::collection::vec(any::<u8>(), 0..2048)) {
            for opts in [ReadOptions::default(), ReadOptions { recover_truncated: true, ..Default::default() }] {
                let _ = read_recording(&bytes, &opts);
                let mut with_magic = MAGIC.to_vec();
                with_magic.extend_from_slice(&bytes);
                let _ = read_recording(&with_magic, &opts);
                with_magic.extend_from_slice(MAGIC);
                let _ = read_recording(&with_magic, &opts);
            }
        }

        #[test]
        fn damaged_recordings_never_panic(
            flips in proptest::collection::vec((any::<proptest::sample::Index>(), 1u8..=255), 1..4),
            cut in any::<proptest::sample::Index>(),
        ) {
            let bytes = write_all(|w| {
                for (i, d) in many_detections(25).iter().enumerate() {
                    w.write(TOPIC_DETECTION, i as i64, d).unwrap();
                    if i % 8 == 7 {
                        w.flush().unwrap();
                    }
                }
            });
            let mut damaged = bytes.clone();
            for (at, mask) in &flips {
                let i = at.index(damaged.len());
                damaged[i] ^= mask;
            }
            for opts in [ReadOptions::default(), ReadOptions { recover_truncated: true, ..Default::default() }] {
                let _ = read_recording(&damaged, &opts);
                let _ = read_recording(&bytes[..cut.index(bytes.len())], &opts);
            }
        }

        #[test]
        fn detections_round_trip(
            msgs in proptest::collection::vec((0i64..1_000_000_000_000_000_000, detection_msg()), 1..20)
        ) {
            let bytes = write_all(|w| {
                for (t, m) in &msgs {
                    w.write(TOPIC_DETECTION, *t, m).unwrap();
                }
            });
            let r = read(&bytes).unwrap();
            let mut expected = msgs.clone();
            expected.sort_by_key(|(t, _)| *t);
            prop_assert_eq!(r.detections.len(), expected.len());
            let exact = json_floats_round_trip_exactly();
            for (got, (t, want)) in r.detections.iter().zip(&expected) {
                prop_assert_eq!(got.t_ns, *t);
                let got = got.msg.as_ref().unwrap();
                prop_assert!(same_detection(got, want, exact), "{:?} != {:?}", got, want);
                let decimals = [want.b_deg, want.c_deg, want.feed_mm_min, want.spindle_rpm,
                    want.x_mm, want.y_mm, want.z_mm];
                if decimals.iter().all(|x| decimal(*x)) {
                    prop_assert_eq!(got, want);
                }
            }
        }
    }
}
