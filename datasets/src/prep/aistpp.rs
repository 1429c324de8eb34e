//! `choreod prep aistpp`: AIST++ motions + music → per-split shards.
//!
//! Music features are computed once per music id on our own front end (choreo-dsp: 16 kHz,
//! log-mel 80 bands, hop 512 → 31.25 frames/s; librosa's onset envelope and beat tracker with the
//! tempo prior from the music id) and aligned to the 30 fps motion frames by linear interpolation
//! at the frame times `i / 30` s (mel frame `k` is centred at `k · 512 / 16000` s, librosa
//! `center=True`). Beats become indices of 30 fps frames (nearest). A sequence is cut to the
//! time both motion and music cover, as EDGE `data/slice.py` slices both to the shorter.
//!
//! With [`PrepOptions::fact35`], each sequence also gets `fact35` `(T, 35)`: the dance field's
//! librosa features (`choreo_dsp::fact35_from_samples`) at 30 fps, whose frame `i` is at `i / 30`
//! s like the motion's, so no alignment but the cut; the beat tracker starts from the music
//! id's BPM (EDGE's and LODGE's rule for AIST++ names).

use std::collections::{BTreeMap, BTreeSet, HashMap};
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicUsize, Ordering};

use choreo_dsp::{
    BeatOptions, DecodeOptions, FACT35_COLUMNS, Fact35Options, LibrosaVersion, MelOptions,
    OnsetOptions,
};
use ndarray::{Array1, Array2, Array3, s};
use rayon::prelude::*;

use super::plan::{
    Candidate, PrepOptions, PrepReport, Progress, RunHeader, SPLITS, ShardJob, Skip, SkipReason,
    ensure_dir, finish_run, group, json_sha256, plan_run, read_name_list, run_plan,
};
use crate::error::{Error, Result, h5_err};
use crate::formats::aistpp::{AISTPP_FPS, AistppMotion, resample_joints};
use crate::formats::h5::{put, put_str};
use crate::utc::now_utc;

/// Shortest sequence kept, seconds: EDGE's training window (`EDGE.py` horizon 5 s).
pub const AISTPP_MIN_SECONDS: f32 = 5.0;
/// Longest sequence kept, seconds: AIST++ takes are under a minute; ten minutes of 60 fps joints
/// is 50 MB, so a shard stays bounded whatever the input.
pub const AISTPP_MAX_SECONDS: f32 = 600.0;
/// Rate of the stored training frames and of the aligned music features (EDGE `data/slice.py`
/// stride 2 from 60 fps).
const TRAIN_FPS: f32 = 30.0;
/// Sequences per shard by default: ≈ 60 MB shards for 25 s average sequences.
const DEFAULT_PER_SHARD: usize = 64;

/// Tempo in BPM from an AIST++ music id (`mBR0` → 80, `mHO5` → 135): EDGE
/// `data/audio_extraction/baseline_features.py:_get_tempo` (mint `tools/preprocessing.py`).
pub fn bpm_from_music_id(id: &str) -> Option<f64> {
    let genre = id.get(0..3)?;
    let d: f64 = id.get(3..)?.parse::<u8>().ok()?.into();
    match genre {
        "mBR" | "mPO" | "mLO" | "mMH" | "mLH" | "mWA" | "mKR" | "mJS" | "mJB" => {
            Some(80.0 + 10.0 * d)
        }
        "mHO" => Some(110.0 + 5.0 * d),
        _ => None,
    }
}

/// `gBR_sBM_cAll_d04_mBR0_ch01` → (genre `gBR`, music id `mBR0`); the music id is field 4
/// (google/aistplusplus_api README).
fn parse_name(name: &str) -> Option<(String, String)> {
    let f: Vec<&str> = name.split('_').collect();
    if f.len() != 6 || !f[0].starts_with('g') || !f[4].starts_with('m') {
        return None;
    }
    bpm_from_music_id(f[4])?;
    Some((f[0].to_string(), f[4].to_string()))
}

/// Music features of one track at the analysis rate.
#[derive(Debug, Clone)]
pub struct MusicFeatures {
    /// Log-mel (frames, 80), 31.25 frames/s.
    pub mel: Array2<f32>,
    /// Onset strength per mel frame.
    pub onset: Vec<f32>,
    /// Beat times, seconds.
    pub beat_times_s: Vec<f64>,
    /// Tempo estimated by the beat tracker, BPM.
    pub tempo_bpm: f64,
    /// Track length, seconds.
    pub duration_s: f64,
    /// The fact35 features `(frames, 35)` at 30 fps, when asked for.
    pub fact35: Option<Array2<f32>>,
}

impl MusicFeatures {
    /// Decode `path` and compute the features; `bpm` centres the beat tracker's tempo prior.
    /// `fact35`: also the fact35 set as this librosa computes it.
    pub fn compute(path: &Path, bpm: f64, fact35: Option<LibrosaVersion>) -> Result<Self> {
        let dsp = |e: choreo_dsp::Error| Error::invalid(path, e.to_string());
        let mel_opts = MelOptions::default();
        let audio = choreo_dsp::decode_file(path, &DecodeOptions::default()).map_err(dsp)?;
        let fact35 = match fact35 {
            Some(version) => {
                let opts = Fact35Options {
                    fps: TRAIN_FPS as u32,
                    version,
                    start_bpm: Some(bpm),
                };
                let f =
                    choreo_dsp::fact35_from_samples(&audio.samples, audio.sample_rate, None, &opts)
                        .map_err(dsp)?;
                Some(
                    Array2::from_shape_vec((f.frames, FACT35_COLUMNS), f.data)
                        .map_err(|e| Error::invalid(path, e.to_string()))?,
                )
            }
            None => None,
        };
        let sr = mel_opts.sample_rate;
        let samples = if audio.sample_rate == sr {
            audio.samples
        } else {
            choreo_dsp::resample_to(&audio.samples, audio.sample_rate, sr).map_err(dsp)?
        };
        if samples.is_empty() {
            return Err(Error::invalid(path, "no audio samples"));
        }
        let mel = choreo_dsp::log_mel(&samples, &mel_opts).map_err(dsp)?;
        let onset =
            choreo_dsp::onset_strength(&samples, sr, &OnsetOptions::default()).map_err(dsp)?;
        let mut b = BeatOptions::default();
        b.start_bpm = bpm;
        let beats = choreo_dsp::track_beats_from_onsets(onset.clone(), sr, &b);
        Ok(MusicFeatures {
            mel: mel.t().to_owned(),
            onset,
            beat_times_s: beats.beat_times_s,
            tempo_bpm: beats.tempo_bpm,
            duration_s: samples.len() as f64 / f64::from(sr),
            fact35,
        })
    }

    /// Mel frames per second.
    fn frame_rate() -> f64 {
        let m = MelOptions::default();
        f64::from(m.sample_rate) / m.hop_length as f64
    }

    /// Whole 30 fps frames the track covers.
    fn frames_at(&self, fps: f32) -> usize {
        (self.duration_s * f64::from(fps)).floor() as usize
    }

    /// (mel (n, 80), onset (n,), beat frame indices) at `n` frames of `fps`.
    fn aligned(&self, n: usize, fps: f32) -> (Array2<f32>, Array1<f32>, Vec<i32>) {
        let rate = Self::frame_rate();
        let frames = self.mel.nrows();
        let bands = self.mel.ncols();
        let mut mel = Array2::<f32>::zeros((n, bands));
        let mut onset = Array1::<f32>::zeros(n);
        for i in 0..n {
            // f64 time: 48 s at 31.25 fps, exact enough either way, but cheap.
            let pos = i as f64 / f64::from(fps) * rate;
            let k = (pos.floor() as usize).min(frames.saturating_sub(1));
            let k1 = (k + 1).min(frames.saturating_sub(1));
            let w = ((pos - k as f64).clamp(0.0, 1.0)) as f32;
            for b in 0..bands {
                mel[[i, b]] = self.mel[[k, b]] * (1.0 - w) + self.mel[[k1, b]] * w;
            }
            let o = |j: usize| self.onset.get(j).copied().unwrap_or(0.0);
            onset[i] = o(k) * (1.0 - w) + o(k1) * w;
        }
        let mut beats: Vec<i32> = self
            .beat_times_s
            .iter()
            .map(|t| (t * f64::from(fps)).round() as i64)
            .filter(|f| *f >= 0 && (*f as usize) < n)
            .map(|f| f as i32)
            .collect();
        beats.dedup();
        (mel, onset, beats)
    }
}

/// Per-candidate input: motion file, split, genre, music id, BPM.
#[derive(Debug, Clone)]
struct Item {
    path: PathBuf,
    genre: String,
    music_id: String,
    bpm: f64,
}

/// A processed sequence.
#[derive(Debug)]
struct Sequence {
    genre: String,
    music_id: String,
    bpm: f64,
    tempo_bpm: f64,
    source_frames: usize,
    joints60: Array3<f32>,
    joints30: Array3<f32>,
    mel: Array2<f32>,
    onset: Array1<f32>,
    beats: Vec<i32>,
    fact35: Option<Array2<f32>>,
}

struct Job {
    music: HashMap<String, std::result::Result<MusicFeatures, String>>,
    fact35: Option<LibrosaVersion>,
}

impl ShardJob for Job {
    type Item = Item;
    type Output = Sequence;

    fn process(&self, c: &Candidate<Item>) -> std::result::Result<Sequence, Skip> {
        let it = &c.item;
        let name = c.name.as_str();
        let m = AistppMotion::read(&it.path).map_err(|e| {
            let reason = match e {
                Error::NonFinite { .. } => SkipReason::NonFinite,
                _ => SkipReason::Corrupt,
            };
            Skip::new(name, reason, e.to_string())
        })?;
        let music = match self.music.get(&it.music_id) {
            Some(Ok(f)) => f,
            Some(Err(e)) => return Err(Skip::new(name, SkipReason::MusicUnreadable, e.clone())),
            None => {
                return Err(Skip::new(
                    name,
                    SkipReason::MissingMusic,
                    it.music_id.clone(),
                ));
            }
        };
        let max60 = (AISTPP_MAX_SECONDS * AISTPP_FPS) as usize;
        if m.len() > max60 {
            return Err(Skip::new(
                name,
                SkipReason::TooLong,
                format!("{} frames at 60 fps, more than {max60}", m.len()),
            ));
        }
        let joints = m.joints();
        if joints.iter().any(|v| !v.is_finite()) {
            return Err(Skip::new(
                name,
                SkipReason::NonFinite,
                "forward kinematics gave NaN",
            ));
        }
        let source_frames = joints.shape()[0];
        let step = (AISTPP_FPS / TRAIN_FPS).round() as usize;
        let fact35_frames = music.fact35.as_ref().map_or(usize::MAX, |f| f.nrows());
        let n30 = source_frames
            .div_ceil(step)
            .min(music.frames_at(TRAIN_FPS))
            .min(fact35_frames);
        let min30 = (AISTPP_MIN_SECONDS * TRAIN_FPS) as usize;
        if n30 < min30 {
            return Err(Skip::new(
                name,
                SkipReason::TooShort,
                format!(
                    "{n30} frames at 30 fps shared by motion ({source_frames} at 60 fps) and music ({:.1} s); need {min30}",
                    music.duration_s
                ),
            ));
        }
        let n60 = (n30 * step).min(source_frames);
        let joints60 = joints.slice(s![..n60, .., ..]).to_owned();
        let joints30 = resample_joints(&joints60, AISTPP_FPS, TRAIN_FPS)
            .map_err(|e| Skip::new(name, SkipReason::Corrupt, e.to_string()))?;
        let (mel, onset, beats) = music.aligned(joints30.shape()[0], TRAIN_FPS);
        Ok(Sequence {
            genre: it.genre.clone(),
            music_id: it.music_id.clone(),
            bpm: it.bpm,
            tempo_bpm: music.tempo_bpm,
            source_frames,
            joints60,
            joints30,
            mel,
            onset,
            beats,
            fact35: music
                .fact35
                .as_ref()
                .map(|f| f.slice(s![..n30, ..]).to_owned()),
        })
    }

    fn write(&self, path: &Path, file: &hdf5::File, outputs: &[(String, Sequence)]) -> Result<u64> {
        put_str(path, file, "dataset", "aistpp")?;
        put(path, file, "fps", TRAIN_FPS)?;
        put(path, file, "source_fps", AISTPP_FPS)?;
        if let Some(version) = self.fact35 {
            put_str(path, file, "music_features", "fact35")?;
            put_str(path, file, "fact35_librosa", version.release())?;
        }
        let mut frames = 0u64;
        for (name, q) in outputs {
            let g = group(path, file, name)?;
            put_str(path, &g, "name", name)?;
            put_str(path, &g, "genre", &q.genre)?;
            put_str(path, &g, "music_id", &q.music_id)?;
            put(path, &g, "bpm", q.bpm)?;
            put(path, &g, "tempo_bpm", q.tempo_bpm)?;
            put(path, &g, "source_frames", q.source_frames as u64)?;
            let e = || h5_err(path);
            let b = || g.new_dataset_builder();
            b().with_data(&q.joints60).create("joints60").map_err(e())?;
            b().with_data(&q.joints30).create("joints30").map_err(e())?;
            b().with_data(&q.mel).create("mel").map_err(e())?;
            b().with_data(&q.onset).create("onset").map_err(e())?;
            let beats = Array1::from(q.beats.clone());
            b().with_data(&beats).create("beats").map_err(e())?;
            if let Some(f) = &q.fact35 {
                b().with_data(f).create("fact35").map_err(e())?;
            }
            frames += q.joints30.shape()[0] as u64;
        }
        Ok(frames)
    }
}

/// Prepare AIST++ at `root` into `out_dir`; see the module docs of [`crate::prep`].
///
/// Fatal errors: unreadable root, missing `motions/` or split lists, an output directory holding
/// shards of other parameters, write failures. Bad sequences are skips in the report.
pub fn prepare_aistpp(
    root: &Path,
    out_dir: &Path,
    opts: &PrepOptions,
    progress: &(dyn Fn(Progress) + Sync),
) -> Result<PrepReport> {
    let started_utc = now_utc();
    let motions = root.join("motions");
    let mut files: Vec<(String, PathBuf)> = Vec::new();
    for e in std::fs::read_dir(&motions).map_err(crate::error::io_err(&motions))? {
        let e = e.map_err(crate::error::io_err(&motions))?;
        let p = e.path();
        if p.extension().is_some_and(|x| x == "pkl")
            && let Some(stem) = p.file_stem()
        {
            files.push((stem.to_string_lossy().into_owned(), p));
        }
    }
    files.sort();
    let ignore_path = root.join("ignore_list.txt");
    let ignore: BTreeSet<String> = if ignore_path.exists() {
        read_name_list(&ignore_path)?.into_iter().collect()
    } else {
        BTreeSet::new()
    };
    let mut split_of: BTreeMap<String, &'static str> = BTreeMap::new();
    let mut notes = Vec::new();
    for split in SPLITS {
        let p = root.join("splits").join(format!("crossmodal_{split}.txt"));
        for n in read_name_list(&p)? {
            if let Some(prev) = split_of.insert(n.clone(), split) {
                notes.push(format!(
                    "{n} is listed in {prev} and {split}; using {split}"
                ));
            }
        }
    }
    let have: BTreeSet<&str> = files.iter().map(|(n, _)| n.as_str()).collect();
    let unlisted = split_of
        .keys()
        .filter(|n| !have.contains(n.as_str()))
        .count();
    if unlisted > 0 {
        notes.push(format!("{unlisted} split entries have no motion file"));
    }
    let music_dir = opts.music_dir.clone().unwrap_or_else(|| root.join("music"));
    let mut skips = Vec::new();
    let mut by_split: BTreeMap<&'static str, Vec<Candidate<Item>>> = BTreeMap::new();
    for (name, path) in &files {
        if ignore.contains(name) {
            skips.push(Skip::new(name, SkipReason::Ignored, "ignore_list.txt"));
            continue;
        }
        let Some(split) = split_of.get(name) else {
            skips.push(Skip::new(
                name,
                SkipReason::NotInSplit,
                "splits/crossmodal_*.txt",
            ));
            continue;
        };
        let Some((genre, music_id)) = parse_name(name) else {
            skips.push(Skip::new(
                name,
                SkipReason::BadName,
                "expected gXX_sXX_cAll_dXX_mXXN_chXX",
            ));
            continue;
        };
        let wav = music_dir.join(format!("{music_id}.wav"));
        if !wav.is_file() {
            skips.push(Skip::new(
                name,
                SkipReason::MissingMusic,
                wav.display().to_string(),
            ));
            continue;
        }
        let bpm = bpm_from_music_id(&music_id).unwrap_or(120.0);
        by_split.entry(split).or_default().push(Candidate {
            name: name.clone(),
            item: Item {
                path: path.clone(),
                genre,
                music_id,
                bpm,
            },
        });
    }
    let (per_shard, shards, inputs_sha256) = plan_run(by_split, opts, DEFAULT_PER_SHARD);
    let mel = MelOptions::default();
    let mut parameters = serde_json::json!({
        "dataset": "aistpp",
        "sequences_per_shard": per_shard,
        "source_fps": AISTPP_FPS,
        "fps": TRAIN_FPS,
        "min_seconds": AISTPP_MIN_SECONDS,
        "max_seconds": AISTPP_MAX_SECONDS,
        "mel": {"sample_rate": mel.sample_rate, "n_fft": mel.n_fft, "hop_length": mel.hop_length,
                "n_mels": mel.n_mels, "fmin": mel.fmin, "fmax": mel.fmax, "top_db": mel.top_db},
        "alignment": "linear interpolation of mel/onset at frame times i/30 s; beats rounded to frames",
        "inputs_sha256": inputs_sha256,
    });
    // Only when asked for: runs without it keep the parameters (and shards) they had.
    if let Some(version) = opts.fact35 {
        parameters["music_features"] = serde_json::json!({
            "set": "fact35", "librosa": version.release(), "fps": TRAIN_FPS,
            "start_bpm": "the music id's BPM"
        });
    }
    let params_sha = json_sha256(&parameters);
    ensure_dir(out_dir)?;

    // Music once per id, only for shards this run still has to write.
    let mut needed: BTreeMap<String, (PathBuf, f64)> = BTreeMap::new();
    for s in shards.iter().filter(|s| opts.part.owns(s.global)) {
        if super::plan::finished(out_dir, &s.file_name(), &params_sha)?.is_some() {
            continue;
        }
        for c in &s.items {
            needed.entry(c.item.music_id.clone()).or_insert_with(|| {
                (
                    music_dir.join(format!("{}.wav", c.item.music_id)),
                    c.item.bpm,
                )
            });
        }
    }
    let done = AtomicUsize::new(0);
    let total = needed.len();
    progress(Progress {
        stage: "music",
        done: 0,
        total,
    });
    let pool = rayon::ThreadPoolBuilder::new()
        .num_threads(opts.jobs)
        .build()
        .map_err(|source| Error::ThreadPool {
            threads: opts.jobs,
            source,
        })?;
    let music: HashMap<String, std::result::Result<MusicFeatures, String>> = pool.install(|| {
        needed
            .par_iter()
            .map(|(id, (path, bpm))| {
                let r = MusicFeatures::compute(path, *bpm, opts.fact35).map_err(|e| e.to_string());
                let d = done.fetch_add(1, Ordering::Relaxed) + 1;
                progress(Progress {
                    stage: "music",
                    done: d,
                    total,
                });
                (id.clone(), r)
            })
            .collect()
    });
    let job = Job {
        music,
        fact35: opts.fact35,
    };
    let outcome = run_plan(&job, &shards, out_dir, &params_sha, opts, progress)?;
    let header = RunHeader {
        dataset: "aistpp",
        parameters,
        parameters_sha256: params_sha,
        started_utc,
        files_found: files.len(),
        notes,
    };
    finish_run(out_dir, opts.part, header, &shards, outcome, skips, None)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn bpm_follows_edge_get_tempo() {
        assert_eq!(bpm_from_music_id("mBR0"), Some(80.0));
        assert_eq!(bpm_from_music_id("mJB5"), Some(130.0));
        assert_eq!(bpm_from_music_id("mHO5"), Some(135.0));
        assert_eq!(bpm_from_music_id("mHO0"), Some(110.0));
        assert_eq!(bpm_from_music_id("mXX1"), None);
        assert_eq!(bpm_from_music_id("mBR"), None);
    }

    #[test]
    fn names_parse_to_genre_and_music() {
        assert_eq!(
            parse_name("gBR_sBM_cAll_d04_mBR0_ch01"),
            Some(("gBR".to_string(), "mBR0".to_string()))
        );
        assert_eq!(parse_name("gBR_sBM_cAll_d04_xBR0_ch01"), None);
        assert_eq!(parse_name("random"), None);
    }

    #[test]
    fn alignment_interpolates_at_frame_times() {
        // mel value = frame index, so the aligned value is the fractional mel position.
        let frames = 100;
        let f = MusicFeatures {
            mel: Array2::from_shape_fn((frames, 2), |(k, _)| k as f32),
            onset: (0..frames).map(|k| k as f32).collect(),
            beat_times_s: vec![0.0, 0.5, 1.01, 99.0],
            tempo_bpm: 120.0,
            duration_s: frames as f64 / 31.25,
            fact35: None,
        };
        let (mel, onset, beats) = f.aligned(60, 30.0);
        for i in [0usize, 1, 7, 59] {
            let expect = i as f32 / 30.0 * 31.25;
            // f32 interpolation of values < 100: error ≪ 1e-4.
            assert!((mel[[i, 1]] - expect).abs() < 1e-4, "{i}: {}", mel[[i, 1]]);
            assert!((onset[i] - expect).abs() < 1e-4);
        }
        // 1.01 s → frame 30.3 → 30; 99 s is past the 60 frames.
        assert_eq!(beats, vec![0, 15, 30]);
        assert_eq!(f.frames_at(30.0), 96);
    }
}
