//! Reading untrusted HDF5 motion files in a child process.
//!
//! libhdf5 is a C parser: on crafted files Debian's 1.10.8 reads past its buffers and dies with
//! SIGSEGV (a chunk stored shorter than its nominal size, a global-heap string whose length was
//! bit-flipped). Checks before reading catch what they can; this catches the rest. Once a
//! program calls [`isolate_motion_reads`], every [`crate::read_motion_file`] in it runs the
//! reader in a child process (the program itself, re-executed with a hidden verb that calls
//! [`answer_isolated_read`]) under a memory, CPU and wall-clock limit, and decodes the child's
//! answer — a small header and raw arrays on its stdout — with bounds. When the child dies, the
//! caller gets [`Error::ReaderDied`] and carries on.
//!
//! The answer on the child's stdout:
//!
//! ```text
//! "choreod-isolated-read 1\n"
//! u32 LE   length of the header
//! JSON     the header: Ok(motion header: fps, skeleton, shapes, provenance ...) or Err(message)
//! f32 LE   joints (T, J, 3), then features (T', D) and mel (F, 80) when the header has them
//! f64 LE   a prep shard sequence's music beat times (B,), seconds, when the header has them
//! ```

use std::ffi::OsString;
use std::io::{Read, Write};
use std::os::unix::process::CommandExt;
use std::path::{Path, PathBuf};
use std::process::{Command, ExitStatus, Stdio};
use std::sync::OnceLock;
use std::time::{Duration, Instant};

use ndarray::{Array2, Array3};
use serde::{Deserialize, Serialize};

use crate::error::{Error, Result};
use crate::formats::motion_file::{Features, MelAttachment, MotionFile, Provenance};
use crate::limits::{elements, max_elements};
use crate::metrics::ShardSequence;
use crate::metrics::inputs::check_shard_beats;
use crate::skeleton::SkeletonKind;

const MAGIC: &[u8] = b"choreod-isolated-read 1\n";
/// Longest header accepted: joint names (at most 1024) and provenance strings fit many times.
const MAX_HEADER_BYTES: usize = 16 << 20;
/// Bytes of the child's stderr kept for the log (its last words: libhdf5's or the allocator's).
const MAX_STDERR_BYTES: usize = 4096;

/// The limits a reader child runs under.
#[derive(Debug, Clone)]
#[non_exhaustive]
pub struct ReaderLimits {
    /// Wall-clock time the parent waits before killing the child. Reading a motion file at the
    /// element cap takes a few seconds; a child still busy after this is stuck. Default: 60 s.
    pub wall: Duration,
    /// CPU seconds (`RLIMIT_CPU`) the child may use. Default: 30.
    pub cpu_seconds: u64,
}

impl Default for ReaderLimits {
    fn default() -> Self {
        Self {
            wall: Duration::from_secs(60),
            cpu_seconds: 30,
        }
    }
}

/// Address space (`RLIMIT_AS`) of a reader child under the element cap `max_elements`: 1 GiB
/// for the program, libhdf5 and its caches, plus 16 bytes per allowed value (the f32 array,
/// libhdf5's chunk buffer and a conversion copy, with room to spare). Default cap: 3 GiB.
pub fn memory_limit(max_elements: usize) -> u64 {
    (1u64 << 30).saturating_add((max_elements as u64).saturating_mul(16))
}

/// How to start a reader child: `program args... REQUEST MAX_ELEMENTS -- FILE`, where REQUEST
/// is [`ReadRequest::as_arg`] and MAX_ELEMENTS the parent's element cap.
#[derive(Debug, Clone)]
pub struct IsolatedReader {
    program: PathBuf,
    args: Vec<OsString>,
    limits: ReaderLimits,
}

static INSTALLED: OnceLock<IsolatedReader> = OnceLock::new();

/// From now on, read every motion file of this process through `reader` (once per process;
/// later calls are ignored).
pub fn isolate_motion_reads(reader: IsolatedReader) {
    let _ = INSTALLED.set(reader);
}

/// The reader installed by [`isolate_motion_reads`], if any.
pub(crate) fn installed() -> Option<&'static IsolatedReader> {
    INSTALLED.get()
}

impl IsolatedReader {
    /// A reader that runs `program` with `args` (then `REQUEST MAX_ELEMENTS -- FILE`); the
    /// program must call [`answer_isolated_read`] for them.
    pub fn new(
        program: impl Into<PathBuf>,
        args: impl IntoIterator<Item = impl Into<OsString>>,
        limits: ReaderLimits,
    ) -> Self {
        Self {
            program: program.into(),
            args: args.into_iter().map(Into::into).collect(),
            limits,
        }
    }

    /// Read the motion file `path` in a child process.
    ///
    /// Errors: what the reader says about the file ([`Error::ReadInChild`]),
    /// [`Error::ReaderDied`] when the child crashed, ran out of time or memory, or answered
    /// something that is not an answer, [`Error::ReaderFailed`] when it exited with an error of
    /// its own (its message relayed). All fail this file only.
    pub fn read(&self, path: &Path) -> Result<MotionFile> {
        self.read_motion(path, &ReadRequest::Motion)
    }

    /// The sequence names of the `choreod prep` shard `path` (sorted, `_stats` left out), read
    /// in a child process. Errors as [`Self::read`].
    pub fn read_shard_sequences(&self, path: &Path) -> Result<Vec<String>> {
        let answer = self.ask(path, &ReadRequest::ShardSequences)?;
        match decode_header(&answer) {
            Ok((Header::Sequences(names), [])) => Ok(names),
            Ok((Header::Refused(message), _)) => Err(Error::ReadInChild {
                path: path.to_path_buf(),
                message,
            }),
            Ok(_) => Err(nonsense(path, "not a list of sequences")),
            Err(reason) => Err(nonsense(path, &reason)),
        }
    }

    /// The sequence `name` of the `choreod prep` shard `path` (its motion and music beats),
    /// read in a child process; the beats are checked here as in the child
    /// ([`check_shard_beats`]). Errors as [`Self::read`].
    pub fn read_shard_sequence(&self, path: &Path, name: &str) -> Result<ShardSequence> {
        let answer = self.ask(path, &ReadRequest::ShardSequence(name.to_string()))?;
        match decode_sequence(path, name, &answer) {
            Ok(result) => result,
            Err(reason) => Err(nonsense(path, &reason)),
        }
    }

    fn read_motion(&self, path: &Path, request: &ReadRequest) -> Result<MotionFile> {
        let answer = self.ask(path, request)?;
        match decode(path, &answer) {
            Ok(result) => result,
            Err(reason) => Err(nonsense(path, &reason)),
        }
    }

    /// The root `format` attribute of the HDF5 file `path` (`None` without one), read in a
    /// child process: which reader a file is for is decided without opening it here.
    pub fn read_format(&self, path: &Path) -> Result<Option<String>> {
        let answer = self.ask(path, &ReadRequest::Format)?;
        match decode_header(&answer) {
            Ok((Header::Format(format), [])) => Ok(format),
            Ok((Header::Refused(message), _)) => Err(Error::ReadInChild {
                path: path.to_path_buf(),
                message,
            }),
            Ok(_) => Err(nonsense(path, "not a format")),
            Err(reason) => Err(nonsense(path, &reason)),
        }
    }

    /// Run the child for `path` and return its answer, checked only for size.
    fn ask(&self, path: &Path, request: &ReadRequest) -> Result<Vec<u8>> {
        let cap = max_elements();
        let mut command = Command::new(&self.program);
        #[allow(unsafe_code)] // pre_exec is unsafe: the hook runs between fork and exec.
        // SAFETY: the closure makes only async-signal-safe system calls (close_range, getrlimit,
        // fcntl) and allocates nothing, as a pre-exec hook must.
        unsafe {
            command.pre_exec(inherit_only_standard_streams)
        };
        let mut child = command
            .args(&self.args)
            .arg(request.as_arg())
            .arg(cap.to_string())
            .arg("--")
            .arg(path)
            .stdin(Stdio::null())
            .stdout(Stdio::piped())
            .stderr(Stdio::piped())
            .spawn()
            .map_err(|source| Error::Io {
                path: self.program.clone(),
                source,
            })?;
        // Drain both pipes while waiting, each up to what a valid answer can hold: three f32
        // arrays within the element cap, and f64 beats, at most one per frame (a frame of
        // joints is at least 3 values).
        let max_answer =
            MAGIC.len() + 4 + MAX_HEADER_BYTES + cap.saturating_mul(3 * 4) + cap / 3 * 8;
        let stdout = child.stdout.take().map(|s| drain(s, max_answer + 1));
        let stderr = child.stderr.take().map(|s| drain(s, MAX_STDERR_BYTES));
        let deadline = Instant::now() + self.limits.wall;
        let status = loop {
            match child.try_wait() {
                Ok(Some(status)) => break Some(status),
                Ok(None) if Instant::now() >= deadline => {
                    let _ = child.kill();
                    let _ = child.wait();
                    break None;
                }
                Ok(None) => std::thread::sleep(Duration::from_millis(5)),
                Err(source) => {
                    let _ = child.kill();
                    return Err(Error::Io {
                        path: path.to_path_buf(),
                        source,
                    });
                }
            }
        };
        let answer = stdout.and_then(|h| h.join().ok()).unwrap_or_default();
        let last_words = stderr.and_then(|h| h.join().ok()).unwrap_or_default();
        let died = |what: String| {
            let last_words = String::from_utf8_lossy(&last_words);
            tracing::debug!(file = %path.display(), what, stderr = %last_words.trim_end(), "HDF5 reader child");
            Err(Error::ReaderDied {
                path: path.to_path_buf(),
                what,
            })
        };
        let Some(status) = status else {
            return died(format!(
                "did not finish within {} s",
                self.limits.wall.as_secs()
            ));
        };
        if let Some(code) = status.code().filter(|c| *c != 0) {
            // The child said why on stderr (e.g. a limit it could not set): relay that.
            return Err(Error::ReaderFailed {
                path: path.to_path_buf(),
                status: code,
                message: last_line(&last_words),
            });
        }
        if let Some(what) = abnormal(status) {
            return died(what);
        }
        if answer.len() > max_answer {
            return died(format!("answered more than {max_answer} bytes"));
        }
        Ok(answer)
    }
}

/// What the parent asks the child.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum ReadRequest {
    /// The whole motion file.
    Motion,
    /// Only the root `format` attribute.
    Format,
    /// The sequence names of a `choreod prep` shard.
    ShardSequences,
    /// One sequence of a `choreod prep` shard, as a motion.
    ShardSequence(String),
}

/// Prefix of a [`ReadRequest::ShardSequence`] argument, before the sequence's name.
const SEQUENCE_ARG: &str = "sequence:";

impl ReadRequest {
    /// The request as the child's argument.
    pub fn as_arg(&self) -> String {
        match self {
            ReadRequest::Motion => "motion".into(),
            ReadRequest::Format => "format".into(),
            ReadRequest::ShardSequences => "sequences".into(),
            ReadRequest::ShardSequence(name) => format!("{SEQUENCE_ARG}{name}"),
        }
    }

    /// The request of a child's argument ([`ReadRequest::as_arg`]).
    pub fn from_arg(arg: &str) -> Option<Self> {
        if let Some(name) = arg.strip_prefix(SEQUENCE_ARG) {
            return Some(ReadRequest::ShardSequence(name.to_string()));
        }
        [
            ReadRequest::Motion,
            ReadRequest::Format,
            ReadRequest::ShardSequences,
        ]
        .into_iter()
        .find(|r| r.as_arg() == arg)
    }
}

/// Longest message relayed from a child's stderr, in characters.
const MAX_RELAYED_CHARS: usize = 300;

/// The last non-empty line of a child's stderr, at most [`MAX_RELAYED_CHARS`] characters,
/// control characters escaped (it may name a hostile file).
fn last_line(stderr: &[u8]) -> String {
    let text = String::from_utf8_lossy(stderr);
    let line = text
        .lines()
        .rev()
        .map(str::trim)
        .find(|l| !l.is_empty())
        .unwrap_or("(no message)");
    let mut out: String = line
        .chars()
        .take(MAX_RELAYED_CHARS)
        .flat_map(|c| {
            let escaped: Vec<char> = if c.is_control() {
                c.escape_default().collect()
            } else {
                vec![c]
            };
            escaped
        })
        .collect();
    if line.chars().count() > MAX_RELAYED_CHARS {
        out.push('…');
    }
    out
}

/// An answer that is not one.
fn nonsense(path: &Path, reason: &str) -> Error {
    Error::ReaderDied {
        path: path.to_path_buf(),
        what: format!("answered nonsense ({reason})"),
    }
}

/// Read a pipe to its end, keeping at most `cap` bytes (the rest is read and dropped, so the
/// child never blocks on a full pipe).
fn drain(pipe: impl Read + Send + 'static, cap: usize) -> std::thread::JoinHandle<Vec<u8>> {
    std::thread::spawn(move || {
        let mut pipe = pipe;
        let mut kept = Vec::new();
        let _ = (&mut pipe).take(cap as u64).read_to_end(&mut kept);
        let _ = std::io::copy(&mut pipe, &mut std::io::sink());
        kept
    })
}

/// How the child ended, when a signal or something else than an exit status ended it.
fn abnormal(status: ExitStatus) -> Option<String> {
    use std::os::unix::process::ExitStatusExt;
    if let Some(signal) = status.signal() {
        let cause = match signal {
            // RLIMIT_CPU's soft limit.
            24 => " (its CPU time limit)",
            _ => "",
        };
        return Some(format!(
            "crashed (signal {signal} {}{cause})",
            signal_name(signal)
        ));
    }
    match status.code() {
        Some(_) => None,
        None => Some("stopped".to_string()),
    }
}

/// The usual name of a Linux signal number.
fn signal_name(signal: i32) -> &'static str {
    match signal {
        1 => "SIGHUP",
        2 => "SIGINT",
        3 => "SIGQUIT",
        4 => "SIGILL",
        5 => "SIGTRAP",
        6 => "SIGABRT",
        7 => "SIGBUS",
        8 => "SIGFPE",
        9 => "SIGKILL",
        11 => "SIGSEGV",
        13 => "SIGPIPE",
        15 => "SIGTERM",
        24 => "SIGXCPU",
        25 => "SIGXFSZ",
        31 => "SIGSYS",
        _ => "signal",
    }
}

/// The header of an answer.
#[derive(Debug, Serialize, Deserialize)]
enum Header {
    // Boxed: a motion's header is large beside the other answers.
    Motion(Box<MotionHeader>),
    /// A prep shard's sequence: its motion, and how many beat times follow its arrays (`None`:
    /// the sequence has no `beats`).
    Sequence(Box<MotionHeader>, Option<usize>),
    Format(Option<String>),
    Sequences(Vec<String>),
    Refused(String),
}

/// Everything of a [`MotionFile`] but its arrays, with their shapes.
#[derive(Debug, Serialize, Deserialize)]
struct MotionHeader {
    fps: f32,
    skeleton: String,
    joint_names: Vec<String>,
    parents: Vec<i32>,
    joints: [usize; 3],
    features: Option<FeaturesHeader>,
    mel: Option<MelHeader>,
    provenance: Option<Provenance>,
    generator: String,
}

#[derive(Debug, Serialize, Deserialize)]
struct FeaturesHeader {
    shape: [usize; 2],
    representation: String,
    normalized: bool,
}

#[derive(Debug, Serialize, Deserialize)]
struct MelHeader {
    shape: [usize; 2],
    sample_rate: u32,
    n_fft: u32,
    hop: u32,
    fmin: f32,
    fmax: f32,
}

/// Mark every descriptor above the standard streams close-on-exec, in the forked child just
/// before it runs the reader. Libraries open files without close-on-exec (libhdf5 does, and
/// holds an flock on each): a reader spawned while another thread writes a motion file would
/// otherwise keep that file — and its lock — open for its whole life, so the finished file
/// could not be opened ("unable to lock file", seen in CI), and a hostile input's reader would
/// hold the daemon's open outputs.
#[allow(unsafe_code)] // FFI: close_range, getrlimit and fcntl on descriptor numbers.
fn inherit_only_standard_streams() -> std::io::Result<()> {
    // SAFETY: plain system calls on descriptor numbers; none is dereferenced.
    let all = unsafe {
        libc::syscall(
            libc::SYS_close_range,
            3u32,
            u32::MAX,
            libc::CLOSE_RANGE_CLOEXEC,
        )
    };
    if all == 0 {
        return Ok(());
    }
    // Kernels before 5.11: one descriptor at a time, up to the process's limit.
    let mut limit = libc::rlimit {
        rlim_cur: 0,
        rlim_max: 0,
    };
    // SAFETY: `limit` is a valid rlimit to write into.
    let max_fd = if unsafe { libc::getrlimit(libc::RLIMIT_NOFILE, &mut limit) } == 0 {
        limit.rlim_cur.min(1 << 20) as i32
    } else {
        1024
    };
    for fd in 3..max_fd {
        // SAFETY: fcntl on a number that is not open fails with EBADF and changes nothing.
        unsafe { libc::fcntl(fd, libc::F_SETFD, libc::FD_CLOEXEC) };
    }
    Ok(())
}

/// The child's side: limit this process (address space, CPU, no core file), read what
/// `request` asks of `path` in it and write the answer to `out`.
/// A refusal is an answer too; only a failure to set a limit or to write is an error (the
/// parent relays the child's message).
pub fn answer_isolated_read(
    path: &Path,
    max_elements: usize,
    request: ReadRequest,
    limits: &ReaderLimits,
    out: &mut impl Write,
) -> std::io::Result<()> {
    use rustix::process::{Resource, Rlimit, getrlimit, setrlimit};
    // Only ever lower a limit: one the caller already set lower (`prlimit`, a systemd unit)
    // stays, since raising a hard limit is refused.
    let lower = |resource: Resource, soft: u64, hard: u64| {
        let cap = |v: u64| getrlimit(resource).maximum.map_or(v, |m| v.min(m));
        setrlimit(
            resource,
            Rlimit {
                current: Some(cap(soft)),
                maximum: Some(cap(hard)),
            },
        )
    };
    let memory = memory_limit(max_elements);
    lower(Resource::As, memory, memory)?;
    // The soft limit sends SIGXCPU (reported as such); the hard one a second later SIGKILL.
    lower(Resource::Cpu, limits.cpu_seconds, limits.cpu_seconds + 1)?;
    // A crash on a hostile file is expected here: no core dump for each one.
    lower(Resource::Core, 0, 0)?;
    crate::limits::set_max_elements(max_elements);
    let motion = |read: Result<MotionFile>| match read {
        Ok(motion) => encode(&motion),
        Err(e) => encode_header(&Header::Refused(e.to_string())),
    };
    let answer = match request {
        ReadRequest::Format => encode_header(&Header::Format(root_format(path))),
        ReadRequest::Motion => motion(crate::formats::motion_file::read_motion_file(path)),
        ReadRequest::ShardSequences => match crate::metrics::inputs::shard_sequences(path) {
            Ok(names) => encode_header(&Header::Sequences(names)),
            Err(e) => encode_header(&Header::Refused(e.to_string())),
        },
        ReadRequest::ShardSequence(name) => {
            match crate::metrics::inputs::shard_sequence(path, &name) {
                Ok(sequence) => encode_sequence(&sequence),
                Err(e) => encode_header(&Header::Refused(e.to_string())),
            }
        }
    };
    out.write_all(&answer)?;
    out.flush()
}

/// The root `format` attribute of an HDF5 file, read in this process; `None` when the file does
/// not open or has none.
pub(crate) fn root_format(path: &Path) -> Option<String> {
    let file = crate::formats::h5::h5_file().open(path).ok()?;
    let format = file.attr("format").ok()?;
    let text: hdf5::types::VarLenUnicode = format.read_scalar().ok()?;
    Some(text.as_str().to_string())
}

fn encode_header(header: &Header) -> Vec<u8> {
    let json = serde_json::to_vec(header).unwrap_or_default();
    let mut out = Vec::with_capacity(MAGIC.len() + 4 + json.len());
    out.extend_from_slice(MAGIC);
    out.extend_from_slice(&(json.len() as u32).to_le_bytes());
    out.extend_from_slice(&json);
    out
}

fn encode(m: &MotionFile) -> Vec<u8> {
    let mut out = encode_header(&Header::Motion(Box::new(motion_header(m))));
    push_arrays(m, &mut out);
    out
}

fn encode_sequence(sequence: &ShardSequence) -> Vec<u8> {
    let beats = sequence.beat_times_s.as_deref();
    let header = Header::Sequence(
        Box::new(motion_header(&sequence.motion)),
        beats.map(<[f64]>::len),
    );
    let mut out = encode_header(&header);
    push_arrays(&sequence.motion, &mut out);
    for t in beats.unwrap_or_default() {
        out.extend_from_slice(&t.to_le_bytes());
    }
    out
}

fn motion_header(m: &MotionFile) -> MotionHeader {
    let shape2 = |a: &Array2<f32>| [a.nrows(), a.ncols()];
    let j = m.joints.shape();
    MotionHeader {
        fps: m.fps,
        skeleton: m.skeleton.name().to_string(),
        joint_names: m.skeleton.joint_names(),
        parents: m.skeleton.parents().to_vec(),
        joints: [j[0], j[1], j[2]],
        features: m.features.as_ref().map(|f| FeaturesHeader {
            shape: shape2(&f.data),
            representation: f.representation.clone(),
            normalized: f.normalized,
        }),
        mel: m.mel.as_ref().map(|a| MelHeader {
            shape: shape2(&a.data),
            sample_rate: a.sample_rate,
            n_fft: a.n_fft,
            hop: a.hop,
            fmin: a.fmin,
            fmax: a.fmax,
        }),
        provenance: m.provenance.clone(),
        generator: m.generator.clone(),
    }
}

/// The motion's arrays, f32 LE, in the order the header lists them.
fn push_arrays(m: &MotionFile, out: &mut Vec<u8>) {
    let features = m.features.iter().flat_map(|f| f.data.iter());
    let mel = m.mel.iter().flat_map(|a| a.data.iter());
    for v in m.joints.iter().chain(features).chain(mel) {
        out.extend_from_slice(&v.to_le_bytes());
    }
}

/// An answer's header and the bytes after it.
fn decode_header(bytes: &[u8]) -> std::result::Result<(Header, &[u8]), String> {
    let rest = bytes
        .strip_prefix(MAGIC)
        .ok_or("no answer header (the child printed something else, or nothing)")?;
    let (len, rest) = rest.split_at_checked(4).ok_or("truncated header length")?;
    let len = u32::from_le_bytes([len[0], len[1], len[2], len[3]]) as usize;
    if len > MAX_HEADER_BYTES {
        return Err(format!("a header of {len} bytes"));
    }
    let (json, data) = rest.split_at_checked(len).ok_or("truncated header")?;
    let header: Header = serde_json::from_slice(json).map_err(|e| format!("header: {e}"))?;
    Ok((header, data))
}

/// The parent's side: the answer `bytes` for `path` as the reader's result, or why the answer
/// is not one (`Err(reason)`). Every length is checked before anything is allocated for it.
fn decode(path: &Path, bytes: &[u8]) -> std::result::Result<Result<MotionFile>, String> {
    match decode_header(bytes)? {
        (Header::Refused(message), _) => Ok(Err(refused(path, message))),
        (Header::Motion(h), data) => {
            Ok(decode_arrays(path, *h, None, data)?.map(|(motion, _)| motion))
        }
        _ => Err("not a motion".into()),
    }
}

/// [`decode`] for the answer to [`ReadRequest::ShardSequence`] `name`: the motion, and its
/// beats checked as the child checks a shard's ([`check_shard_beats`]).
fn decode_sequence(
    path: &Path,
    name: &str,
    bytes: &[u8],
) -> std::result::Result<Result<ShardSequence>, String> {
    match decode_header(bytes)? {
        (Header::Refused(message), _) => Ok(Err(refused(path, message))),
        (Header::Sequence(h, beats), data) => Ok(decode_arrays(path, *h, beats, data)?.and_then(
            |(motion, beat_times_s)| {
                if let Some(beats) = &beat_times_s {
                    check_shard_beats(path, name, beats, &motion)?;
                }
                Ok(ShardSequence {
                    motion,
                    beat_times_s,
                })
            },
        )),
        _ => Err("not a shard sequence".into()),
    }
}

fn refused(path: &Path, message: String) -> Error {
    Error::ReadInChild {
        path: path.to_path_buf(),
        message,
    }
}

/// A decoded motion, and the beat times that came with it.
type Decoded = (MotionFile, Option<Vec<f64>>);

/// The arrays after a motion header `h` (and `beats` beat times, at most one per frame),
/// then the motion checked as a file's.
fn decode_arrays(
    path: &Path,
    h: MotionHeader,
    beats: Option<usize>,
    mut data: &[u8],
) -> std::result::Result<Result<Decoded>, String> {
    let mut take = |what: &str, shape: &[usize]| -> std::result::Result<Vec<f32>, String> {
        let n = match elements(path, what, shape) {
            Ok(n) => n,
            Err(e) => return Err(e.to_string()),
        };
        let (values, rest) = data
            .split_at_checked(n.saturating_mul(4))
            .ok_or_else(|| format!("{what}: fewer values than its shape {shape:?}"))?;
        data = rest;
        Ok(values
            .chunks_exact(4)
            .map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]]))
            .collect())
    };
    let joints = take("joints", &h.joints)?;
    let features = match &h.features {
        Some(f) => Some((take("features", &f.shape)?, f)),
        None => None,
    };
    let mel = match &h.mel {
        Some(m) => Some((take("mel", &m.shape)?, m)),
        None => None,
    };
    let beat_times_s = match beats {
        Some(n) if n > h.joints[0] => {
            return Err(format!(
                "{n} beats for {} frames (at most one per frame)",
                h.joints[0]
            ));
        }
        Some(n) => {
            let (values, rest) = data
                .split_at_checked(n * 8)
                .ok_or_else(|| format!("fewer than {n} beat times"))?;
            data = rest;
            Some(
                values
                    .chunks_exact(8)
                    .map(|b| f64::from_le_bytes([b[0], b[1], b[2], b[3], b[4], b[5], b[6], b[7]]))
                    .collect(),
            )
        }
        None => None,
    };
    if !data.is_empty() {
        return Err(format!("{} bytes after the arrays", data.len()));
    }
    let joints = Array3::from_shape_vec(h.joints, joints).map_err(|e| e.to_string())?;
    let features = match features {
        Some((values, f)) => Some(Features {
            data: Array2::from_shape_vec(f.shape, values).map_err(|e| e.to_string())?,
            representation: f.representation.clone(),
            normalized: f.normalized,
        }),
        None => None,
    };
    let mel = match mel {
        Some((values, m)) => Some(MelAttachment {
            data: Array2::from_shape_vec(m.shape, values).map_err(|e| e.to_string())?,
            sample_rate: m.sample_rate,
            n_fft: m.n_fft,
            hop: m.hop,
            fmin: m.fmin,
            fmax: m.fmax,
        }),
        None => None,
    };
    let motion = MotionFile {
        fps: h.fps,
        skeleton: SkeletonKind::from_parts(&h.skeleton, h.joint_names, h.parents),
        joints,
        features,
        mel,
        provenance: h.provenance,
        generator: h.generator,
    };
    // The child checked it already; a child that lies gets the same checks here.
    Ok(motion.validate(path).map(|()| (motion, beat_times_s)))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn motion() -> MotionFile {
        let joints = Array3::from_shape_fn((5, 24, 3), |(t, j, c)| (t * 100 + j * 3 + c) as f32);
        let mut m = MotionFile::from_joints(60.0, SkeletonKind::Smpl24, joints);
        m.features = Some(Features {
            data: Array2::from_shape_fn((4, 263), |(t, d)| (t * 263 + d) as f32 * 0.5),
            representation: "humanml3d263".into(),
            normalized: true,
        });
        m.mel = Some(MelAttachment {
            data: Array2::from_shape_fn((7, 80), |(t, d)| -(t as f32) - d as f32),
            sample_rate: 16_000,
            n_fft: 2048,
            hop: 512,
            fmin: 0.0,
            fmax: 8000.0,
        });
        m.provenance = Some(Provenance {
            source_name: "song\n.ogg".into(),
            seed: 7,
            content_guidance: Some(1.5),
            ..Provenance::default()
        });
        m
    }

    #[test]
    fn an_answer_decodes_to_the_motion_it_encodes() {
        let m = motion();
        let back = decode(Path::new("x.h5"), &encode(&m)).unwrap().unwrap();
        assert_eq!(back, m);
        let refused = encode_header(&Header::Refused("x.h5: no frames".into()));
        let e = decode(Path::new("x.h5"), &refused).unwrap().unwrap_err();
        assert_eq!(e.to_string(), "x.h5: no frames");
    }

    #[test]
    fn a_short_long_or_lying_answer_is_refused_before_allocating() {
        let p = Path::new("x.h5");
        let good = encode(&motion());
        assert!(
            decode(p, &good[..good.len() - 1]).is_err(),
            "one byte short"
        );
        let mut long = good.clone();
        long.push(0);
        assert!(decode(p, &long).is_err(), "one byte over");
        assert!(decode(p, b"hello").is_err());
        assert!(decode(p, &good[..MAGIC.len() + 2]).is_err());
        // A header claiming 2^40 frames: refused by the element cap, not allocated.
        let json = String::from_utf8_lossy(&good[MAGIC.len() + 4..]).into_owned();
        let at = json.find("\"joints\":[5,").unwrap();
        let mut lying = Vec::from(MAGIC);
        let header = json[..json.find("}}").unwrap() + 2].replacen(
            &json[at..at + 12],
            "\"joints\":[1099511627776,",
            1,
        );
        lying.extend_from_slice(&(header.len() as u32).to_le_bytes());
        lying.extend_from_slice(header.as_bytes());
        let e = decode(p, &lying).unwrap_err();
        assert!(e.contains("exceeds the limit"), "{e}");
        // A NaN the child should never send is caught by the same checks as a file's.
        let mut m = motion();
        m.joints[[1, 2, 0]] = f32::NAN;
        let e = decode(p, &encode(&m)).unwrap().unwrap_err();
        assert!(matches!(e, Error::NonFinite { .. }), "{e}");
    }

    fn sequence() -> ShardSequence {
        let joints = Array3::from_shape_fn((5, 24, 3), |(t, j, c)| (t * 100 + j * 3 + c) as f32);
        ShardSequence {
            // 5 frames at 60 fps: beats up to 1/12 s.
            motion: MotionFile::from_joints(60.0, SkeletonKind::Smpl24, joints),
            beat_times_s: Some(vec![0.0, 1.0 / 30.0, 0.07]),
        }
    }

    /// `seq`'s answer with a header that says `beats` beat times follow the arrays, and `values`.
    fn sequence_answer(seq: &ShardSequence, beats: Option<usize>, values: &[f64]) -> Vec<u8> {
        let header = Header::Sequence(Box::new(motion_header(&seq.motion)), beats);
        let mut out = encode_header(&header);
        push_arrays(&seq.motion, &mut out);
        for v in values {
            out.extend_from_slice(&v.to_le_bytes());
        }
        out
    }

    #[test]
    fn a_sequence_answer_decodes_to_its_motion_and_beats() {
        let p = Path::new("x.h5");
        let s = sequence();
        let back = decode_sequence(p, "seq", &encode_sequence(&s))
            .unwrap()
            .unwrap();
        assert_eq!(back, s, "beat times to the last bit");
        let none = ShardSequence {
            beat_times_s: None,
            ..sequence()
        };
        let back = decode_sequence(p, "seq", &encode_sequence(&none))
            .unwrap()
            .unwrap();
        assert_eq!(back, none);
        // Each request takes only its own kind of answer.
        let e = decode_sequence(p, "seq", &encode(&s.motion)).unwrap_err();
        assert_eq!(e, "not a shard sequence");
        let e = decode(p, &encode_sequence(&s)).unwrap_err();
        assert_eq!(e, "not a motion");
    }

    #[test]
    fn lying_or_bad_beats_in_an_answer_are_refused_before_use() {
        let p = Path::new("x.h5");
        let s = sequence();
        // A count beyond one beat per frame: refused before anything is allocated for it.
        let e = decode_sequence(p, "seq", &sequence_answer(&s, Some(1 << 40), &[])).unwrap_err();
        assert_eq!(
            e,
            "1099511627776 beats for 5 frames (at most one per frame)"
        );
        let e = decode_sequence(p, "seq", &sequence_answer(&s, Some(6), &[0.0; 6])).unwrap_err();
        assert!(e.contains("6 beats for 5 frames"), "{e}");
        // Fewer or more bytes than the count.
        let e = decode_sequence(p, "seq", &sequence_answer(&s, Some(3), &[0.0, 0.01])).unwrap_err();
        assert_eq!(e, "fewer than 3 beat times");
        let e = decode_sequence(p, "seq", &sequence_answer(&s, Some(1), &[0.0, 0.01])).unwrap_err();
        assert_eq!(e, "8 bytes after the arrays");
        let e = decode_sequence(p, "seq", &sequence_answer(&s, None, &[0.0])).unwrap_err();
        assert_eq!(e, "8 bytes after the arrays");
        // Values a shard's beats never hold: the file's error, as a shard read here says it.
        for (values, want) in [
            (vec![0.0, f64::NAN], "beat 1 at NaN s is not finite"),
            (vec![-0.5], "beat 0 at -0.5 s is before the start"),
            (
                vec![0.05, 0.04],
                "beat 1 at 0.04 s is before the beat before it",
            ),
            (vec![0.1], "beat 0 at 0.1 s is after the end"),
        ] {
            let answer = sequence_answer(&s, Some(values.len()), &values);
            let e = decode_sequence(p, "seq", &answer).unwrap().unwrap_err();
            assert!(matches!(e, Error::Invalid { .. }), "{e:?}");
            assert_eq!(
                e.to_string(),
                format!("x.h5: sequence 'seq': beats: {want} (the sequence is 0.083 s)")
            );
        }
    }

    #[test]
    fn a_child_that_sends_lying_beats_is_one_error_naming_the_file() {
        // The whole parent path (pipes, size bound, decoding, checks): a "child" that prints a
        // prepared answer.
        let dir = tempfile::tempdir().unwrap();
        let answer = dir.path().join("answer");
        std::fs::write(&answer, sequence_answer(&sequence(), Some(1), &[-3.0])).unwrap();
        let reader = reader("exec cat \"$4\"", Duration::from_secs(20));
        let e = reader
            .read_shard_sequence(&answer, "seq")
            .unwrap_err()
            .to_string();
        assert_eq!(
            e,
            format!(
                "{}: sequence 'seq': beats: beat 0 at -3 s is before the start (the sequence is 0.083 s)",
                answer.display()
            )
        );
        std::fs::write(&answer, encode_sequence(&sequence())).unwrap();
        let back = reader.read_shard_sequence(&answer, "seq").unwrap();
        assert_eq!(back, sequence());
    }

    #[test]
    fn every_request_survives_the_childs_argument() {
        for r in [
            ReadRequest::Motion,
            ReadRequest::Format,
            ReadRequest::ShardSequences,
            ReadRequest::ShardSequence("gBR_sBM_cAll_d04_mBR0_ch01".into()),
            // A sequence name is the shard's: anything HDF5 allows, prefixes included.
            ReadRequest::ShardSequence("sequence:format \n".into()),
        ] {
            assert_eq!(ReadRequest::from_arg(&r.as_arg()), Some(r.clone()), "{r:?}");
        }
        assert_eq!(ReadRequest::from_arg("motions"), None);
    }

    fn reader(script: &str, wall: Duration) -> IsolatedReader {
        let limits = ReaderLimits {
            wall,
            ..ReaderLimits::default()
        };
        // sh -c SCRIPT sh REQUEST N -- FILE: the script sees them as $1..$4.
        IsolatedReader::new("/bin/sh", ["-c", script, "sh"], limits)
    }

    #[test]
    fn the_child_inherits_no_descriptor_but_its_standard_streams() {
        // libhdf5 opens without close-on-exec and holds an flock: a motion file being written
        // while a reader starts.
        let dir = tempfile::tempdir().unwrap();
        let header = MotionFile::from_joints(
            30.0,
            crate::skeleton::SkeletonKind::Smpl24,
            Array3::zeros((2, 24, 3)),
        );
        let open = crate::formats::motion_file::MotionAppender::create(
            &dir.path().join("being-written.h5"),
            &header,
        )
        .unwrap();
        let script = "for f in /proc/$$/fd/*; do readlink \"$f\"; done | grep -q being-written \
             && echo inherited >&2 || echo 'not inherited' >&2; exit 3";
        let e = reader(script, Duration::from_secs(20))
            .read(Path::new("x.h5"))
            .unwrap_err();
        drop(open);
        let Error::ReaderFailed { message, .. } = &e else {
            panic!("{e:?}")
        };
        assert_eq!(message, "not inherited");
    }

    #[test]
    fn a_child_that_dies_or_hangs_is_one_error_naming_the_file_and_how() {
        let p = Path::new("dir/x.h5");
        let e = reader("kill -SEGV $$", Duration::from_secs(20))
            .read(p)
            .unwrap_err();
        assert!(matches!(e, Error::ReaderDied { .. }), "{e}");
        assert_eq!(
            e.to_string(),
            "dir/x.h5: the HDF5 reader crashed (signal 11 SIGSEGV) — the file is corrupt or hostile"
        );
        let t0 = Instant::now();
        let e = reader("exec sleep 30", Duration::from_millis(300))
            .read(p)
            .unwrap_err()
            .to_string();
        assert!(e.contains("did not finish within 0 s"), "{e}");
        assert!(
            t0.elapsed() < Duration::from_secs(10),
            "killed, not waited for"
        );
        let e = reader("echo oops; exit 0", Duration::from_secs(20))
            .read(p)
            .unwrap_err()
            .to_string();
        assert!(e.contains("answered nonsense (no answer header"), "{e}");
        // An exit with an error of its own: its last stderr line relayed, escaped and bounded.
        let e = reader(
            "echo 'setrlimit: Operation not permitted' >&2; printf 'a\\033[31mb%0400d\\n' 0 >&2; exit 3",
            Duration::from_secs(20),
        )
        .read(p)
        .unwrap_err();
        let Error::ReaderFailed {
            status, message, ..
        } = &e
        else {
            panic!("{e:?}")
        };
        assert_eq!(*status, 3);
        assert!(message.starts_with("a\\u{1b}[31mb000"), "{message}");
        // 300 characters, the escape character written as the 6 of `\u{1b}`, and an ellipsis.
        assert_eq!(message.chars().count(), MAX_RELAYED_CHARS - 1 + 6 + 1);
        let e = reader(
            "echo 'choreod: error: no limit' >&2; exit 1",
            Duration::from_secs(20),
        )
        .read(p)
        .unwrap_err()
        .to_string();
        assert_eq!(
            e,
            "dir/x.h5: the HDF5 reader failed (exit status 1): choreod: error: no limit"
        );
        // The arguments the child gets, in order.
        let e = reader(
            "test \"$1 $3 $4\" = \"motion -- dir/x.h5\" || exit 9; test \"$2\" -gt 0 || exit 9; kill -ABRT $$",
            Duration::from_secs(20),
        )
        .read(p)
        .unwrap_err()
        .to_string();
        assert!(e.contains("signal 6 SIGABRT"), "{e}");
    }
}
