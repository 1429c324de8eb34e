//! Encoder delay/padding of AAC in MP4 from the audio track's edit list (`moov/trak/edts/elst`).
//!
//! symphonia 0.6's isomp4 reader parses `elst` but does not apply it
//! (`symphonia-format-isomp4:src/atoms/edts.rs`), so AAC in M4A would keep its 1024 priming
//! frames and the padding of the last packet. ffmpeg (which librosa's audioread fallback uses for
//! M4A) honours the edit list: skip `media_time` (media timescale) at the start and play
//! `segment_duration` (movie timescale). ISO/IEC 14496-12 §8.6.6; box layout as in
//! `symphonia-format-isomp4:src/atoms/{elst,mdhd,mvhd}.rs`.
//!
//! Only box headers and the few small boxes needed are read, each bounded by [`MAX_BOX`].

use std::fs::File;
use std::io::{Read, Seek, SeekFrom};
use std::path::Path;

/// Largest leaf box we read into memory (mvhd/mdhd/hdlr/elst are tens of bytes each).
const MAX_BOX: u64 = 1 << 20;
/// Deepest nesting we follow (moov/trak/mdia/... is 4 levels).
const MAX_DEPTH: usize = 6;
/// Most boxes visited in one file (real files have a few dozen; bounds hostile ones).
const MAX_BOXES: usize = 100_000;

/// Trim of the audio track, in media-timescale units.
#[derive(Debug, Clone, Copy, PartialEq)]
pub(crate) struct EditTrim {
    /// Frames to skip at the start (in `media_timescale` units).
    pub skip: u64,
    /// Frames to keep after the skip, if the edit says (in `media_timescale` units).
    pub keep: Option<u64>,
    /// Timescale of `skip`/`keep` (the track's mdhd timescale).
    pub media_timescale: u32,
}

#[derive(Debug, Default)]
struct Trak {
    is_audio: bool,
    media_timescale: Option<u32>,
    /// (segment_duration in movie timescale, media_time in media timescale)
    edit: Option<(u64, i64)>,
}

struct Walker {
    file: File,
    boxes: usize,
    movie_timescale: Option<u32>,
    traks: Vec<Trak>,
}

/// Read the audio track's edit-list trim. `None` when the file is not MP4, has no edit list, or
/// anything looks wrong (then the caller decodes untrimmed, as symphonia does).
pub(crate) fn audio_edit_trim(path: &Path) -> Option<EditTrim> {
    let file = File::open(path).ok()?;
    let len = file.metadata().ok()?.len();
    let mut w = Walker {
        file,
        boxes: 0,
        movie_timescale: None,
        traks: Vec::new(),
    };
    w.walk(0, len, 0, false).ok()?;
    let movie_ts = w.movie_timescale?;
    let trak = w.traks.iter().find(|t| t.is_audio)?;
    let media_ts = trak.media_timescale?;
    let (seg, media_time) = trak.edit?;
    if media_time < 0 || movie_ts == 0 || media_ts == 0 {
        return None;
    }
    let keep = (seg > 0).then(|| {
        // segment_duration is in the movie timescale; round to the nearest media unit.
        ((u128::from(seg) * u128::from(media_ts) + u128::from(movie_ts) / 2) / u128::from(movie_ts))
            as u64
    });
    Some(EditTrim {
        skip: media_time as u64,
        keep,
        media_timescale: media_ts,
    })
}

impl Walker {
    fn read_exact_at(&mut self, pos: u64, buf: &mut [u8]) -> std::io::Result<()> {
        self.file.seek(SeekFrom::Start(pos))?;
        self.file.read_exact(buf)
    }

    fn leaf(&mut self, pos: u64, size: u64) -> std::io::Result<Vec<u8>> {
        if size > MAX_BOX {
            return Err(std::io::Error::other("box too large"));
        }
        let mut buf = vec![0u8; size as usize];
        self.read_exact_at(pos, &mut buf)?;
        Ok(buf)
    }

    fn walk(&mut self, start: u64, end: u64, depth: usize, in_trak: bool) -> std::io::Result<()> {
        if depth > MAX_DEPTH {
            return Ok(());
        }
        let mut pos = start;
        while pos + 8 <= end {
            self.boxes += 1;
            if self.boxes > MAX_BOXES {
                return Err(std::io::Error::other("too many boxes"));
            }
            let mut h = [0u8; 8];
            self.read_exact_at(pos, &mut h)?;
            let size32 = u64::from(u32::from_be_bytes([h[0], h[1], h[2], h[3]]));
            let kind = [h[4], h[5], h[6], h[7]];
            let (size, header) = match size32 {
                0 => (end - pos, 8),
                1 => {
                    let mut l = [0u8; 8];
                    self.read_exact_at(pos + 8, &mut l)?;
                    (u64::from_be_bytes(l), 16)
                }
                s => (s, 8),
            };
            if size < header || pos + size > end {
                return Err(std::io::Error::other("bad box size"));
            }
            let body = (pos + header, size - header);
            match &kind {
                b"moov" => self.walk(body.0, body.0 + body.1, depth + 1, false)?,
                b"trak" => {
                    self.traks.push(Trak::default());
                    self.walk(body.0, body.0 + body.1, depth + 1, true)?;
                }
                b"mdia" | b"edts" if in_trak => {
                    self.walk(body.0, body.0 + body.1, depth + 1, true)?
                }
                b"mvhd" => {
                    let b = self.leaf(body.0, body.1)?;
                    // version(1) flags(3), then v0: ctime(4) mtime(4) timescale(4); v1: 8+8+4.
                    let off = if b.first() == Some(&1) { 20 } else { 12 };
                    self.movie_timescale = be_u32(&b, off);
                }
                b"mdhd" if in_trak => {
                    let b = self.leaf(body.0, body.1)?;
                    let off = if b.first() == Some(&1) { 20 } else { 12 };
                    if let Some(t) = self.traks.last_mut() {
                        t.media_timescale = be_u32(&b, off);
                    }
                }
                b"hdlr" if in_trak => {
                    let b = self.leaf(body.0, body.1)?;
                    // version/flags(4) pre_defined(4) handler_type(4)
                    if let Some(t) = self.traks.last_mut() {
                        t.is_audio = b.get(8..12) == Some(b"soun".as_slice());
                    }
                }
                b"elst" if in_trak => {
                    let b = self.leaf(body.0, body.1)?;
                    let v1 = b.first() == Some(&1);
                    let count = be_u32(&b, 4).unwrap_or(0);
                    // Use the first non-empty edit (media_time != -1); empty edits are delays.
                    let entry = if v1 { 20 } else { 12 };
                    for i in 0..count.min(16) as usize {
                        let o = 8 + i * entry;
                        let (seg, mt) = if v1 {
                            (be_u64(&b, o), be_u64(&b, o + 8).map(|v| v as i64))
                        } else {
                            (
                                be_u32(&b, o).map(u64::from),
                                be_u32(&b, o + 4).map(|v| i64::from(v as i32)),
                            )
                        };
                        let (Some(seg), Some(mt)) = (seg, mt) else {
                            break;
                        };
                        if mt >= 0 {
                            if let Some(t) = self.traks.last_mut() {
                                t.edit = Some((seg, mt));
                            }
                            break;
                        }
                    }
                }
                _ => {}
            }
            pos += size;
        }
        Ok(())
    }
}

fn be_u32(b: &[u8], off: usize) -> Option<u32> {
    b.get(off..off + 4)
        .map(|s| u32::from_be_bytes([s[0], s[1], s[2], s[3]]))
}

fn be_u64(b: &[u8], off: usize) -> Option<u64> {
    b.get(off..off + 8)
        .and_then(|s| s.try_into().ok())
        .map(u64::from_be_bytes)
}
