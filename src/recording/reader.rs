//! Reading logs back: [`LogReader`] (streaming, tolerant of damage), [`read_log`] (all of it)
//! and [`read_index`] (the summary only).
//!
//! The reader walks the file from its start with mcap's sans-io linear reader and pulls bytes
//! from the source in pieces of at most [`ReadOptions::read_size`], so a length field damaged
//! into something huge costs no memory beyond the file's real size. Each chunk's CRC is checked
//! before any of its messages is yielded: the messages of a cut or damaged chunk are never
//! yielded, and what comes out is always a prefix of what was written. A file cut anywhere
//! therefore reads up to its last complete chunk, then ends with [`ReadError::Truncated`].
//!
//! Metadata and attachment records sit in the data section, so the linear reader finds them
//! whether or not the file has a summary (a killed writer leaves none).

use std::collections::{BTreeMap, BTreeSet, HashMap};
use std::fs::File;
use std::io::{BufReader, Read, Seek, SeekFrom};
use std::path::Path;
use std::sync::Arc;

use mcap::records::Record;
use mcap::sans_io::{LinearReadEvent, LinearReader, LinearReaderOptions, SummaryReadEvent, SummaryReader, SummaryReaderOptions};

const MAGIC: &[u8] = b"\x89MCAP0\r\n";

/// How a [`LogReader`] reads.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct ReadOptions {
    /// Largest record (or chunk, compressed or not) accepted, bytes; a longer one is damage.
    pub record_length_limit: usize,
    /// Most bytes pulled from the source per read.
    pub read_size: usize,
}

impl Default for ReadOptions {
    fn default() -> Self {
        ReadOptions { record_length_limit: 64 << 20, read_size: 256 << 10 }
    }
}

/// A schema of the log.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct SchemaInfo {
    pub id: u16,
    pub name: String,
    pub encoding: String,
    pub data: Vec<u8>,
}

/// A channel of the log.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct ChannelInfo {
    pub id: u16,
    pub topic: String,
    pub message_encoding: String,
    pub metadata: BTreeMap<String, String>,
    /// `None`: schemaless (schema id 0), as the raw frame channels.
    pub schema: Option<Arc<SchemaInfo>>,
}

/// One message of the log.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct LoggedMessage {
    pub channel: Arc<ChannelInfo>,
    pub sequence: u32,
    pub log_time_ns: u64,
    pub publish_time_ns: u64,
    pub data: Vec<u8>,
}

impl LoggedMessage {
    pub fn topic(&self) -> &str {
        &self.channel.topic
    }

    /// Decodes a JSON message (`/vehicle_<id>/internals`, `/links/stats`).
    pub fn json<T: serde::de::DeserializeOwned>(&self) -> Result<T, serde_json::Error> {
        serde_json::from_slice(&self.data)
    }

    /// Decodes a protobuf message (the Foxglove channels), e.g. `foxglove::messages::LocationFix`.
    pub fn protobuf<T: prost::Message + Default>(&self) -> Result<T, prost::DecodeError> {
        T::decode(self.data.as_slice())
    }
}

/// A metadata record of the log.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct LoggedMetadata {
    pub name: String,
    pub entries: BTreeMap<String, String>,
}

/// An attachment of the log.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct LoggedAttachment {
    pub name: String,
    pub media_type: String,
    pub log_time_ns: u64,
    pub create_time_ns: u64,
    pub data: Vec<u8>,
}

/// How a read ended.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum LogEnd {
    /// The whole file was read, summary and footer included: its writer finished it.
    Complete,
    /// The file stops early (its writer was killed, or it was cut): every complete chunk before
    /// the cut was read. `summary` says nothing: there is none.
    Truncated,
    /// A record could not be read (a bad CRC, a malformed record): everything before it was read.
    Corrupt { reason: String },
}

/// Why a read stopped before the end of a complete log.
#[derive(Debug, thiserror::Error)]
pub enum ReadError {
    #[error("cannot open the log {path}: {source}")]
    Open { path: String, source: std::io::Error },
    #[error("reading the log failed after {messages_read} messages ({bytes_read} bytes): {source}")]
    Io { messages_read: u64, bytes_read: u64, source: std::io::Error },
    #[error("not an MCAP file (its first bytes are not the MCAP magic)")]
    NotMcap,
    #[error(
        "the log is truncated after {messages_read} messages ({bytes_read} bytes, last log time {last_log_time_ns:?} ns): \
         it has no summary (its writer was killed or did not finish); everything up to its last complete chunk was read"
    )]
    Truncated { messages_read: u64, bytes_read: u64, last_log_time_ns: Option<u64> },
    #[error("the log is damaged after {messages_read} messages ({bytes_read} bytes read): {reason}")]
    Corrupt { messages_read: u64, bytes_read: u64, reason: String },
    #[error(
        "the log {path} has no summary section (its writer did not finish, e.g. it was killed): read it with LogReader / read_log"
    )]
    NoSummary { path: String },
    #[error("the summary of the log {path} is unreadable: {reason}")]
    BadSummary { path: String, reason: String },
}

/// Reads a log in file order: an iterator of messages that ends with at most one error saying
/// how far it got (see [`ReadError::Truncated`], [`ReadError::Corrupt`]). Metadata and
/// attachments met on the way are kept ([`LogReader::metadata`], [`LogReader::attachments`]).
///
/// ```no_run
/// # fn main() -> Result<(), cooploc::recording::ReadError> {
/// let mut reader = cooploc::recording::LogReader::open("node.mcap")?.with_topics(["/coop/2/rx"]);
/// for message in reader.by_ref() {
///     match message {
///         Ok(m) => println!("{} {} bytes", m.log_time_ns, m.data.len()),
///         Err(e) => eprintln!("{e}"), // e.g. truncated: everything before was read
///     }
/// }
/// println!("{:?}", reader.end());
/// # Ok(()) }
/// ```
pub struct LogReader<R> {
    source: R,
    reader: LinearReader,
    options: ReadOptions,
    topics: Option<BTreeSet<String>>,
    schemas: HashMap<u16, Arc<SchemaInfo>>,
    channels: HashMap<u16, Arc<ChannelInfo>>,
    metadata: Vec<LoggedMetadata>,
    attachments: Vec<LoggedAttachment>,
    in_summary: bool,
    messages_read: u64,
    last_log_time_ns: Option<u64>,
    bytes_read: u64,
    /// The first bytes of the source (to tell a non-MCAP file from a cut one).
    head: Vec<u8>,
    end: Option<LogEnd>,
}

impl LogReader<BufReader<File>> {
    /// Opens the log at `path`.
    pub fn open(path: impl AsRef<Path>) -> Result<Self, ReadError> {
        let path = path.as_ref();
        let file = File::open(path).map_err(|source| ReadError::Open { path: path.display().to_string(), source })?;
        Ok(Self::new(BufReader::new(file)))
    }
}

impl<R: Read> LogReader<R> {
    pub fn new(source: R) -> Self {
        Self::with_options(source, ReadOptions::default())
    }

    pub fn with_options(source: R, options: ReadOptions) -> Self {
        let linear = LinearReaderOptions::default()
            .with_prevalidate_chunk_crcs(true)
            .with_record_length_limit(options.record_length_limit);
        LogReader {
            source,
            reader: LinearReader::new_with_options(linear),
            options,
            topics: None,
            schemas: HashMap::new(),
            channels: HashMap::new(),
            metadata: Vec::new(),
            attachments: Vec::new(),
            in_summary: false,
            messages_read: 0,
            last_log_time_ns: None,
            bytes_read: 0,
            head: Vec::new(),
            end: None,
        }
    }

    /// Yields only the messages of these topics (all messages are still read and counted).
    pub fn with_topics<S: Into<String>>(mut self, topics: impl IntoIterator<Item = S>) -> Self {
        self.topics = Some(topics.into_iter().map(Into::into).collect());
        self
    }

    /// Metadata records read so far, in file order.
    pub fn metadata(&self) -> &[LoggedMetadata] {
        &self.metadata
    }

    /// Attachments read so far, in file order.
    pub fn attachments(&self) -> &[LoggedAttachment] {
        &self.attachments
    }

    /// Channels seen so far, by id.
    pub fn channels(&self) -> impl Iterator<Item = &Arc<ChannelInfo>> {
        self.channels.values()
    }

    /// Messages read so far (of every topic).
    pub fn messages_read(&self) -> u64 {
        self.messages_read
    }

    /// How the read ended; `None` while it goes on.
    pub fn end(&self) -> Option<&LogEnd> {
        self.end.as_ref()
    }

    /// Ends the read with `error`, recording how it ended.
    fn stop(&mut self, error: ReadError) -> Option<Result<LoggedMessage, ReadError>> {
        self.end = Some(match &error {
            ReadError::Truncated { .. } => LogEnd::Truncated,
            other => LogEnd::Corrupt { reason: other.to_string() },
        });
        Some(Err(error))
    }

    fn corrupt(&mut self, reason: String) -> Option<Result<LoggedMessage, ReadError>> {
        let error = ReadError::Corrupt { messages_read: self.messages_read, bytes_read: self.bytes_read, reason };
        self.stop(error)
    }

    /// Maps an error of the mcap reader to ours.
    fn mcap_error(&mut self, e: mcap::McapError) -> Option<Result<LoggedMessage, ReadError>> {
        let head_is_magic_prefix = MAGIC.starts_with(&self.head) || self.head.starts_with(MAGIC);
        if !head_is_magic_prefix {
            return self.stop(ReadError::NotMcap);
        }
        match e {
            mcap::McapError::UnexpectedEof => {
                let error = ReadError::Truncated {
                    messages_read: self.messages_read,
                    bytes_read: self.bytes_read,
                    last_log_time_ns: self.last_log_time_ns,
                };
                self.stop(error)
            }
            other => self.corrupt(other.to_string()),
        }
    }

    /// Handles one record; returns a message to yield, if it is one (of a wanted topic).
    fn record(&mut self, opcode: u8, data: &[u8]) -> Result<Option<LoggedMessage>, String> {
        let record = mcap::parse_record(opcode, data).map_err(|e| format!("record 0x{opcode:02x}: {e}"))?;
        match record {
            Record::DataEnd(_) => self.in_summary = true,
            // Repeated in the summary section; the data section's copies count.
            Record::Schema { .. } | Record::Channel(_) if self.in_summary => {}
            Record::Schema { header, data } => {
                if header.id == 0 {
                    return Err("a schema with id 0".into());
                }
                let schema = SchemaInfo { id: header.id, name: header.name, encoding: header.encoding, data: data.into_owned() };
                match self.schemas.get(&header.id) {
                    Some(known) if **known != schema => return Err(format!("schema {} redefined", header.id)),
                    Some(_) => {}
                    None => {
                        self.schemas.insert(header.id, Arc::new(schema));
                    }
                }
            }
            Record::Channel(c) => {
                let schema = match c.schema_id {
                    0 => None,
                    id => Some(self.schemas.get(&id).cloned().ok_or(format!("channel {} uses unknown schema {id}", c.topic))?),
                };
                let channel =
                    ChannelInfo { id: c.id, topic: c.topic, message_encoding: c.message_encoding, metadata: c.metadata, schema };
                match self.channels.get(&c.id) {
                    Some(known) if **known != channel => return Err(format!("channel {} redefined", c.id)),
                    Some(_) => {}
                    None => {
                        self.channels.insert(c.id, Arc::new(channel));
                    }
                }
            }
            Record::Message { header, data } => {
                let channel = self
                    .channels
                    .get(&header.channel_id)
                    .cloned()
                    .ok_or(format!("a message on unknown channel {}", header.channel_id))?;
                self.messages_read += 1;
                self.last_log_time_ns = Some(header.log_time);
                if self.topics.as_ref().is_none_or(|t| t.contains(&channel.topic)) {
                    return Ok(Some(LoggedMessage {
                        channel,
                        sequence: header.sequence,
                        log_time_ns: header.log_time,
                        publish_time_ns: header.publish_time,
                        data: data.into_owned(),
                    }));
                }
            }
            Record::Metadata(m) => self.metadata.push(LoggedMetadata { name: m.name, entries: m.metadata }),
            Record::Attachment { header, data, .. } => self.attachments.push(LoggedAttachment {
                name: header.name,
                media_type: header.media_type,
                log_time_ns: header.log_time,
                create_time_ns: header.create_time,
                data: data.into_owned(),
            }),
            _ => {}
        }
        Ok(None)
    }
}

impl<R: Read> Iterator for LogReader<R> {
    type Item = Result<LoggedMessage, ReadError>;

    fn next(&mut self) -> Option<Self::Item> {
        if self.end.is_some() {
            return None;
        }
        loop {
            let event = match self.reader.next_event() {
                None => {
                    self.end = Some(LogEnd::Complete);
                    return None;
                }
                Some(Err(e)) => return self.mcap_error(e),
                Some(Ok(event)) => event,
            };
            match event {
                LinearReadEvent::ReadRequest(need) => {
                    let want = need.clamp(1, self.options.read_size.max(1));
                    let buf = self.reader.insert(want);
                    let n = loop {
                        match self.source.read(buf) {
                            Ok(n) => break n,
                            Err(e) if e.kind() == std::io::ErrorKind::Interrupted => continue,
                            Err(source) => {
                                let error =
                                    ReadError::Io { messages_read: self.messages_read, bytes_read: self.bytes_read, source };
                                self.end = Some(LogEnd::Corrupt { reason: error.to_string() });
                                return Some(Err(error));
                            }
                        }
                    };
                    if self.head.len() < MAGIC.len() {
                        let take = n.min(MAGIC.len() - self.head.len());
                        self.head.extend_from_slice(&buf[..take]);
                    }
                    self.bytes_read += n as u64;
                    self.reader.notify_read(n);
                }
                LinearReadEvent::Record { opcode, data } => {
                    let data = data.to_vec();
                    match self.record(opcode, &data) {
                        Ok(Some(message)) => return Some(Ok(message)),
                        Ok(None) => {}
                        Err(reason) => return self.corrupt(reason),
                    }
                }
            }
        }
    }
}

/// Everything [`read_log`] found in a log.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Log {
    /// All messages, in file order.
    pub messages: Vec<LoggedMessage>,
    pub metadata: Vec<LoggedMetadata>,
    pub attachments: Vec<LoggedAttachment>,
    /// All channels, by id.
    pub channels: BTreeMap<u16, Arc<ChannelInfo>>,
    /// Whether the file was complete (summary and footer), cut, or damaged.
    pub end: LogEnd,
}

impl Log {
    /// The messages of one topic, in file order.
    pub fn topic<'a>(&'a self, topic: &'a str) -> impl Iterator<Item = &'a LoggedMessage> + 'a {
        self.messages.iter().filter(move |m| m.channel.topic == topic)
    }

    /// The first metadata record called `name`.
    pub fn metadata_named(&self, name: &str) -> Option<&LoggedMetadata> {
        self.metadata.iter().find(|m| m.name == name)
    }

    /// Whether the writer finished the file (it has its summary).
    pub fn is_complete(&self) -> bool {
        self.end == LogEnd::Complete
    }
}

/// Reads a whole log into memory. A cut or damaged file is not an error: [`Log::end`] says how
/// it ended, and everything before the damage is there. Errors: the file cannot be opened or
/// read, or is not an MCAP file at all.
pub fn read_log(path: impl AsRef<Path>) -> Result<Log, ReadError> {
    read_log_from(LogReader::open(path)?)
}

/// [`read_log`] from any reader.
pub fn read_log_from<R: Read>(mut reader: LogReader<R>) -> Result<Log, ReadError> {
    let mut messages = Vec::new();
    for item in reader.by_ref() {
        match item {
            Ok(m) => messages.push(m),
            Err(e @ (ReadError::NotMcap | ReadError::Io { .. })) => return Err(e),
            Err(_) => {}
        }
    }
    let end = reader.end.clone().unwrap_or(LogEnd::Complete);
    Ok(Log {
        messages,
        channels: reader.channels.iter().map(|(id, c)| (*id, c.clone())).collect(),
        metadata: reader.metadata,
        attachments: reader.attachments,
        end,
    })
}

/// What the summary of a finished log says, read without scanning its messages.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct LogIndex {
    /// All channels, by id.
    pub channels: BTreeMap<u16, Arc<ChannelInfo>>,
    pub message_count: u64,
    /// Message count per topic.
    pub topic_counts: BTreeMap<String, u64>,
    /// Log time of the first and last message, ns (0, 0 when there are none).
    pub start_ns: u64,
    pub end_ns: u64,
    pub chunk_count: u32,
    pub metadata: Vec<LoggedMetadata>,
    pub attachments: Vec<LoggedAttachment>,
}

/// Reads the summary of the log at `path` (channels, counts, metadata, attachments) by seeking,
/// without reading the messages. [`ReadError::NoSummary`] when the file has none (its writer
/// was killed): use [`read_log`] or [`LogReader`] then, which read the same metadata and
/// attachments from the data section.
pub fn read_index(path: impl AsRef<Path>) -> Result<LogIndex, ReadError> {
    let path = path.as_ref();
    let path_str = path.display().to_string();
    let open_err = |source| ReadError::Open { path: path_str.clone(), source };
    let bad = |reason: String| ReadError::BadSummary { path: path_str.clone(), reason };
    let mut file = File::open(path).map_err(open_err)?;
    let size = file.metadata().map_err(open_err)?.len();

    // Not even a footer and its magic: no summary (a cut file), or not an MCAP file at all.
    let mut head = [0u8; 8];
    let n = read_up_to(&mut file, &mut head).map_err(open_err)?;
    if !MAGIC.starts_with(&head[..n]) {
        return Err(ReadError::NotMcap);
    }
    let mut tail = [0u8; 8];
    if size < 8 + 29 + 8
        || file.seek(SeekFrom::End(-8)).is_err()
        || read_up_to(&mut file, &mut tail).map_err(open_err)? < 8
        || tail != MAGIC
    {
        return Err(ReadError::NoSummary { path: path_str });
    }
    file.seek(SeekFrom::Start(0)).map_err(open_err)?;

    let options = SummaryReaderOptions::default().with_file_size(size).with_record_length_limit(256 << 20);
    let mut reader = SummaryReader::new_with_options(options);
    while let Some(event) = reader.next_event() {
        match event.map_err(|e| bad(e.to_string()))? {
            SummaryReadEvent::ReadRequest(need) => {
                let buf = reader.insert(need);
                let n = read_up_to(&mut file, buf).map_err(open_err)?;
                reader.notify_read(n);
            }
            SummaryReadEvent::SeekRequest(to) => {
                let pos = file.seek(to).map_err(open_err)?;
                reader.notify_seeked(pos);
            }
        }
    }
    let summary = reader.finish().ok_or(ReadError::NoSummary { path: path_str.clone() })?;

    let mut schemas: HashMap<u16, Arc<SchemaInfo>> = HashMap::new();
    for (id, s) in &summary.schemas {
        let info = SchemaInfo { id: *id, name: s.name.clone(), encoding: s.encoding.clone(), data: s.data.to_vec() };
        schemas.insert(*id, Arc::new(info));
    }
    let channels: BTreeMap<u16, Arc<ChannelInfo>> = summary
        .channels
        .iter()
        .map(|(id, c)| {
            let info = ChannelInfo {
                id: *id,
                topic: c.topic.clone(),
                message_encoding: c.message_encoding.clone(),
                metadata: c.metadata.clone(),
                schema: c.schema.as_ref().and_then(|s| schemas.get(&s.id).cloned()),
            };
            (*id, Arc::new(info))
        })
        .collect();
    let stats = summary.stats.clone().unwrap_or_default();
    let mut topic_counts = BTreeMap::new();
    for (id, count) in &stats.channel_message_counts {
        if let Some(c) = channels.get(id) {
            *topic_counts.entry(c.topic.clone()).or_insert(0) += count;
        }
    }

    let mut metadata = Vec::new();
    for index in &summary.metadata_indexes {
        match read_record_at(&mut file, index.offset, index.length, size).map_err(&bad)? {
            Record::Metadata(m) => metadata.push(LoggedMetadata { name: m.name, entries: m.metadata }),
            other => return Err(bad(format!("metadata index points at record 0x{:02x}", other.opcode()))),
        }
    }
    let mut attachments = Vec::new();
    for index in &summary.attachment_indexes {
        match read_record_at(&mut file, index.offset, index.length, size).map_err(&bad)? {
            Record::Attachment { header, data, .. } => attachments.push(LoggedAttachment {
                name: header.name,
                media_type: header.media_type,
                log_time_ns: header.log_time,
                create_time_ns: header.create_time,
                data: data.into_owned(),
            }),
            other => return Err(bad(format!("attachment index points at record 0x{:02x}", other.opcode()))),
        }
    }

    Ok(LogIndex {
        channels,
        message_count: stats.message_count,
        topic_counts,
        start_ns: stats.message_start_time,
        end_ns: stats.message_end_time,
        chunk_count: stats.chunk_count,
        metadata,
        attachments,
    })
}

/// Reads as much of `buf` as the source has.
fn read_up_to(r: &mut impl Read, buf: &mut [u8]) -> std::io::Result<usize> {
    let mut filled = 0;
    while filled < buf.len() {
        match r.read(&mut buf[filled..]) {
            Ok(0) => break,
            Ok(n) => filled += n,
            Err(e) if e.kind() == std::io::ErrorKind::Interrupted => {}
            Err(e) => return Err(e),
        }
    }
    Ok(filled)
}

/// Reads and parses the whole record (opcode, length, body) at `offset`.
fn read_record_at(file: &mut File, offset: u64, length: u64, size: u64) -> Result<Record<'static>, String> {
    if length < 9 || offset.checked_add(length).is_none_or(|end| end > size) {
        return Err(format!("an index points outside the file ({offset} + {length} > {size})"));
    }
    let mut buf = vec![0u8; length as usize];
    file.seek(SeekFrom::Start(offset)).map_err(|e| e.to_string())?;
    file.read_exact(&mut buf).map_err(|e| e.to_string())?;
    let body_len = u64::from_le_bytes(buf[1..9].try_into().expect("8 bytes"));
    if body_len != length - 9 {
        return Err(format!("the record at {offset} is {body_len} bytes long, its index says {}", length - 9));
    }
    mcap::parse_record(buf[0], &buf[9..]).map(|r| r.into_owned()).map_err(|e| e.to_string())
}
