//! LODGE's two-stage music to dance (task `lodge`; the package contract is in
//! models/export/README.md). Facts from the official code (github.com/li-ronghui/LODGE,
//! a898e59), cited by file:line; none of its code is here.
//!
//! 1. **Global**: windows of 1024 fact35 frames → 104 keyframes each (13 chunks of 8), DDIM with
//!    guidance 2 (`infer_lodge.py:219-245`, `diffusion.py:262-294`). The keyframes are
//!    un-normalised and their 6D taken through axis-angle and back (`diffusion.py:1040-1090`,
//!    `ax_from_6v` then `ax_to_6v`).
//! 2. **Constraints**: each 256-frame Local window gets 24 keyframe rows (`infer_lodge.py:254-285`):
//!    4 at each end, and two 8-frame chunks placed at rows 28 and 156 with their mirror images
//!    at 60 and 188 (`Local_Module.py:175-224`); contacts and rotations are in-painted, the root
//!    is not.
//! 3. **Local**: windows of 256 frames, DDIM with the guidance ramp `min(2, linspace(0, 4,
//!    50)[i])`, the genre and fresh style noise at every call, clean-value in-painting of the
//!    constrained values after every step but the last (`diffusion.py:491-545`, `--soft 1` of
//!    the README's command). The windows are un-normalised, their 6D re-orthonormalised the same
//!    way, and concatenated (`concat_res.py`).
//!
//! [`LodgeCompat::Official`] reproduces the official run, quirks included; the default
//! [`LodgeCompat::Fixed`] differs in exactly the points [`FIXES`] lists.

use ndarray::{Array2, Array3, Array4, ArrayView2, ArrayView3, Axis, s};

use crate::diffusion::noise::NoiseSource;
use crate::error::{Error, Result};
use crate::package::ModelPackage;
use crate::package::manifest::{LodgeSpec, MinMaxNormalizer, StageLayout};
use choreo_datasets::smplx::{
    LODGE_CONTACTS, LODGE_FEATURES, axis_angle_to_mat, mat_to_axis_angle, mat_to_rot6d,
    rot6d_to_mat,
};

/// Keyframes per chunk (the Global network's 104 = 13 × 8).
const CHUNK: usize = 8;
/// Local windows per Global window (1024 / 256).
const LOCALS_PER_GLOBAL: usize = 4;
/// Keyframe rows one Local window takes (`scale = 8 · (1024/256 − 1)`, infer_lodge.py:271).
const KEYS_PER_LOCAL: usize = CHUNK * (LOCALS_PER_GLOBAL - 1);
/// First column of the root translation, and of the rotations.
const ROOT: usize = LODGE_CONTACTS;
const ROT: usize = LODGE_CONTACTS + 3;
/// Rows of a Local window the keyframe chunks go to (Local_Module.py:204-209): the chunk, its
/// mirror, the next chunk, its mirror.
const CHUNK_ROWS: [usize; 4] = [28, 60, 156, 188];
/// SMPL-X body joints swapped by the mirror (infer_lodge.py:31-33, Local_Module.py:33-35).
const RIGHT_CHAIN: [usize; 8] = [2, 5, 8, 11, 14, 17, 19, 21];
const LEFT_CHAIN: [usize; 8] = [1, 4, 7, 10, 13, 16, 18, 20];
/// Longest song: 20 minutes at 30 fps.
pub const MAX_FRAMES: usize = 20 * 60 * 30;

/// Which behaviour of the official code to follow.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub enum LodgeCompat {
    /// The official output's layout with its bugs mended ([`FIXES`]).
    #[default]
    Fixed,
    /// The official run, quirks included (`--lodge-compat official`).
    Official,
}

/// What the default mode does differently from the official code, one line each (printed by
/// `dance` and listed in the README).
pub const FIXES: [&str; 5] = [
    "the tail under 256 frames is danced (the official code drops it): the music is padded \
     with its last frame to whole windows and the dance cut to the song",
    "every Local window gets its own music (the official code gives the last windows of a \
     song that is not a multiple of 1024 frames the music of the last Global window's start)",
    "the root's x/z continues from window to window (the official windows each start at the \
     origin)",
    "mirrored keyframes are mirrored as motion and then normalised (the official code mirrors \
     normalised values and stores the result un-normalised)",
    "songs under 1024 frames (34.1 s) dance (the official code crashes on them)",
];

/// The draws of a deterministic run (`--init-noise`): every x_T and every style noise.
#[derive(Debug, Clone, PartialEq)]
pub struct LodgeNoise {
    /// `(G, 104, 139)`: x_T of each Global window.
    pub global_x: Array3<f32>,
    /// `(L, 256, 139)`: x_T of each Local window.
    pub local_x: Array3<f32>,
    /// `(steps, 2, L, style)`: per step the unconditional call's then the conditional call's
    /// style noise (model.py:869-873, 947).
    pub local_style: Array4<f32>,
}

/// How to run.
#[derive(Debug, Clone, PartialEq)]
#[non_exhaustive]
pub struct LodgeOptions {
    /// Seed of every draw not given by `init_noise`.
    pub seed: u64,
    /// DDIM steps (default: the package's timesteps).
    pub steps: Option<usize>,
    /// DDIM eta (default: the package's).
    pub eta: Option<f64>,
    /// Genre name, alias or id (default: by tempo, [`default_genre`]).
    pub genre: Option<String>,
    /// Official quirks or the mended default.
    pub compat: LodgeCompat,
    /// Every x_T and style noise.
    pub init_noise: Option<LodgeNoise>,
    /// Windows denoised together (bounds memory).
    pub chunk_windows: usize,
}

impl Default for LodgeOptions {
    fn default() -> Self {
        Self {
            seed: 0,
            steps: None,
            eta: None,
            genre: None,
            compat: LodgeCompat::Fixed,
            init_noise: None,
            chunk_windows: 16,
        }
    }
}

/// Counts of the work done.
#[derive(Debug, Clone, Copy, Default, PartialEq, serde::Serialize)]
#[non_exhaustive]
pub struct LodgeStats {
    /// Global windows.
    pub global_windows: usize,
    /// Local windows.
    pub local_windows: usize,
    /// DDIM steps per stage.
    pub steps: usize,
    /// Denoiser calls (a guided step is one call of 2N rows).
    pub evaluations: usize,
    /// Output frames.
    pub frames: usize,
}

/// A LODGE dance.
#[derive(Debug, Clone)]
#[non_exhaustive]
pub struct LodgeDance {
    /// `(T, 139)` raw (un-normalised) features.
    pub features: Array2<f32>,
    /// `(G, 104, 139)`: the Global stage's final normalised windows.
    pub global_windows: Array3<f32>,
    /// `(L, 256, 139)`: the Local stage's final normalised windows.
    pub local_windows: Array3<f32>,
    /// `(L, 256, 139)` each: the in-painting every Local window was sampled with (values,
    /// normalised, and the 0/1 mask of the rows and columns it holds).
    pub local_constraints: LodgeConstraints,
    /// The genre id danced.
    pub genre: usize,
    /// Why that genre: "given" or the tempo rule.
    pub genre_reason: String,
    /// Sampler settings used.
    pub steps: usize,
    /// DDIM eta used.
    pub eta: f64,
    /// Work done.
    pub stats: LodgeStats,
}

/// The stage a progress report is about.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum LodgeStage {
    /// Keyframes.
    Global,
    /// Full frames.
    Local,
}

/// Where each window's music and keyframes come from.
#[derive(Debug, Clone, PartialEq)]
pub(crate) struct Plan {
    /// Frames of the (padded) music the windows read.
    pub music_frames: usize,
    /// Start frame of each Global window's 1024 frames.
    pub global_starts: Vec<usize>,
    /// Start frame of each Local window's 256 frames.
    pub local_starts: Vec<usize>,
    /// Frames of the finished dance.
    pub out_frames: usize,
}

/// Window layout for `frames` frames of music (infer_lodge.py:211-232).
pub(crate) fn plan(frames: usize, compat: LodgeCompat) -> Result<Plan> {
    let (g, l) = (1024, 256);
    let bad = |reason: String| Error::Input {
        what: "music".into(),
        reason,
    };
    if frames == 0 || frames > MAX_FRAMES {
        return Err(bad(format!(
            "{frames} frames; LODGE dances 1..={MAX_FRAMES} frames (20 minutes at 30 fps)"
        )));
    }
    let (locals, music_frames, out_frames) = match compat {
        // The tail under 256 frames is dropped (infer_lodge.py:211-212); under 1024 frames the
        // Global window is short and single windows take another code path: both crash.
        LodgeCompat::Official => {
            if frames < g {
                return Err(bad(format!(
                    "{frames} frames: the official code needs at least {g} frames (34.1 s) and \
                     crashes below; the default mode dances it"
                )));
            }
            let n = frames / l;
            (n, n * l, n * l)
        }
        LodgeCompat::Fixed => {
            let n = frames.div_ceil(l);
            (n, (n * l).max(g), frames)
        }
    };
    let globals = locals.div_ceil(LOCALS_PER_GLOBAL);
    // The last Global window takes the song's last 1024 frames when the windows do not fill
    // it (infer_lodge.py:221-222).
    let covered = locals * l;
    let global_starts: Vec<usize> = (0..globals)
        .map(|gi| {
            if (gi + 1) * g > covered {
                covered.max(g) - g
            } else {
                gi * g
            }
        })
        .collect();
    let local_starts = (0..locals)
        .map(|k| match compat {
            LodgeCompat::Fixed => k * l,
            // The Local music is the Global windows' music cut in 256s and the first `locals`
            // kept (infer_lodge.py:253-254): after a partial last Global window the windows
            // read that window's first frames instead of their own.
            LodgeCompat::Official => {
                global_starts[k / LOCALS_PER_GLOBAL] + (k % LOCALS_PER_GLOBAL) * l
            }
        })
        .collect();
    Ok(Plan {
        music_frames,
        global_starts,
        local_starts,
        out_frames,
    })
}

/// The 24 keyframe rows of every Local window from the Global stage's raw keyframes
/// `(G, 104, 139)` (infer_lodge.py:250-285): Global window g > 0 starts with the previous
/// window's last chunk; a partial last Global window contributes its last `8 + 24·flag` rows,
/// `flag` = Local windows past the last whole Global window.
pub(crate) fn keyframe_rows(keyframes: ArrayView3<'_, f32>, locals: usize) -> Vec<Array2<f32>> {
    let globals = keyframes.len_of(Axis(0));
    let flag = locals % LOCALS_PER_GLOBAL;
    let mut rows = Vec::with_capacity(locals);
    for gi in 0..globals {
        let this = keyframes.index_axis(Axis(0), gi);
        let n = this.nrows();
        let mut temp = if gi > 0 && gi == globals - 1 && flag != 0 {
            this.slice(s![n - CHUNK - KEYS_PER_LOCAL * flag.., ..])
                .to_owned()
        } else {
            this.to_owned()
        };
        if gi > 0 {
            let prev = keyframes.index_axis(Axis(0), gi - 1);
            temp.slice_mut(s![..CHUNK, ..])
                .assign(&prev.slice(s![n - CHUNK.., ..]));
        }
        let inner = temp.slice(s![CHUNK / 2..temp.nrows() - CHUNK / 2, ..]);
        for item in 0..inner.nrows() / KEYS_PER_LOCAL {
            rows.push(
                inner
                    .slice(s![item * KEYS_PER_LOCAL..(item + 1) * KEYS_PER_LOCAL, ..])
                    .to_owned(),
            );
        }
    }
    rows.truncate(locals);
    rows
}

/// 6D of every joint of a raw frame through axis-angle and back, as the official code does to
/// each output (`ax_from_6v` then `ax_to_6v`): Gram–Schmidt plus float rounding.
fn reorthonormalize(frame: &mut [f32]) {
    for j in 0..(LODGE_FEATURES - ROT) / 6 {
        let at = ROT + 6 * j;
        let d6: [f32; 6] = frame[at..at + 6].try_into().expect("six values");
        let round = mat_to_rot6d(&axis_angle_to_mat(&mat_to_axis_angle(&rot6d_to_mat(&d6))));
        frame[at..at + 6].copy_from_slice(&round);
    }
}

/// The mirror image of frames (infer_lodge.py:31-64 `swap_left_right`, Local_Module.py:191-198):
/// left and right feet and joints swapped, axis-angle y and z negated, root x negated.
fn mirror(frames: ArrayView2<'_, f32>) -> Array2<f32> {
    let mut out = frames.to_owned();
    for (mut o, f) in out.outer_iter_mut().zip(frames.outer_iter()) {
        // Contacts: left ankle, right ankle, left toe, right toe → swapped pairwise.
        for (a, b) in [(0, 1), (1, 0), (2, 3), (3, 2)] {
            o[a] = f[b];
        }
        o[ROOT] = -f[ROOT];
        let mut axis_angles = [[0.0f32; 3]; 22];
        for (j, aa) in axis_angles.iter_mut().enumerate() {
            let at = ROT + 6 * j;
            let d6: [f32; 6] = f.slice(s![at..at + 6]).to_vec().try_into().expect("6");
            *aa = mat_to_axis_angle(&rot6d_to_mat(&d6));
        }
        let mut swapped = axis_angles;
        for (r, l) in RIGHT_CHAIN.iter().zip(LEFT_CHAIN) {
            swapped[*r] = axis_angles[l];
            swapped[l] = axis_angles[*r];
        }
        for (j, aa) in swapped.iter().enumerate() {
            let at = ROT + 6 * j;
            let d6 = mat_to_rot6d(&axis_angle_to_mat(&[aa[0], -aa[1], -aa[2]]));
            for (k, v) in d6.iter().enumerate() {
                o[at + k] = *v;
            }
        }
    }
    out
}

/// A Local window's in-painting: values and a 0/1 mask, `(256, 139)` each.
#[derive(Debug, Clone, PartialEq)]
pub(crate) struct Constraint {
    pub value: Array2<f32>,
    pub mask: Array2<f32>,
}

/// Both stages' final normalised windows and the Local stage's in-painting, as
/// `choreod dance --save-windows` writes them.
#[derive(Debug, Clone, PartialEq)]
pub struct LodgeWindows {
    /// `(G, 104, 139)` Global windows.
    pub global: Array3<f32>,
    /// `(L, 256, 139)` Local windows.
    pub local: Array3<f32>,
    /// What every Local window was in-painted with.
    pub constraints: LodgeConstraints,
}

/// The in-painting of every Local window: values and a 0/1 mask, `(L, 256, 139)` each.
#[derive(Debug, Clone, PartialEq)]
pub struct LodgeConstraints {
    /// Normalised values of the in-painted rows (the end rows keep their root translation,
    /// which the mask leaves free, as the official code does); zero elsewhere.
    pub value: Array3<f32>,
    /// 1 where the value replaces the sample after a step.
    pub mask: Array3<f32>,
}

/// The constraint of one Local window from its 24 raw keyframe rows (Local_Module.py:170-224):
/// normalise; rows 0..4 and 252..256 = the ends (root x and z made relative to their first
/// row); the two 8-row chunks at rows 28 and 156, their mirrors at 60 and 188. Contacts and
/// rotations are constrained, the root translation is not.
pub(crate) fn local_constraint(
    keys: ArrayView2<'_, f32>,
    normalizer: &MinMaxNormalizer,
    frames: usize,
    compat: LodgeCompat,
) -> Constraint {
    let normalize = |rows: ArrayView2<'_, f32>| {
        let mut out = rows.to_owned();
        for mut r in out.outer_iter_mut() {
            for (c, v) in r.iter_mut().enumerate() {
                *v = normalizer.normalize(c, *v);
            }
        }
        out
    };
    let norm = normalize(keys);
    let ends = |rows: ArrayView2<'_, f32>| {
        let mut e = rows.to_owned();
        for c in [ROOT, ROOT + 2] {
            let first = e[[0, c]];
            e.column_mut(c).mapv_inplace(|v| v - first);
        }
        e
    };
    let n = keys.nrows();
    let mid = norm.slice(s![4..n - 4, ..]);
    let mirrored = match compat {
        // Mirrored from the normalised values and stored as the mirror returns them: 6D not
        // normalised again, contacts swapped and root x negated in normalised space.
        LodgeCompat::Official => mirror(mid),
        LodgeCompat::Fixed => normalize(mirror(keys.slice(s![4..n - 4, ..])).view()),
    };
    let mut value = Array2::<f32>::zeros((frames, LODGE_FEATURES));
    let mut mask = Array2::<f32>::zeros((frames, LODGE_FEATURES));
    let half = mid.nrows() / 2;
    let blocks = [
        (0, ends(norm.slice(s![..4, ..]))),
        (frames - 4, ends(norm.slice(s![n - 4.., ..]))),
        (CHUNK_ROWS[0], mid.slice(s![..half, ..]).to_owned()),
        (CHUNK_ROWS[1], mirrored.slice(s![..half, ..]).to_owned()),
        (CHUNK_ROWS[2], mid.slice(s![half.., ..]).to_owned()),
        (CHUNK_ROWS[3], mirrored.slice(s![half.., ..]).to_owned()),
    ];
    for (row, block) in blocks {
        let rows = row..row + block.nrows();
        value.slice_mut(s![rows.clone(), ..]).assign(&block);
        mask.slice_mut(s![rows.clone(), ..LODGE_CONTACTS]).fill(1.0);
        mask.slice_mut(s![rows, ROT..]).fill(1.0);
    }
    Constraint { value, mask }
}

/// The timesteps of `steps` DDIM steps as the official loop makes them, followed by -1:
/// `torch.linspace(-1, T - 1, steps + 1).int()` reversed (diffusion.py:265-267).
pub(crate) fn timesteps(spec: &LodgeSpec<'_>, train: usize, steps: Option<usize>) -> Vec<i64> {
    match steps {
        None => spec.timesteps.iter().copied().chain([-1]).collect(),
        Some(n) => {
            let (a, b) = (-1.0f32, train as f32 - 1.0);
            let step = (b - a) / n as f32;
            (0..=n)
                .rev()
                .map(|i| (a + step * i as f32) as i64)
                .collect()
        }
    }
}

/// alphas_cumprod as LODGE holds it (diffusion.py:82-86): betas rounded to float32, `1 - beta`
/// in float32, then `torch.cumprod`, whose CPU kernel accumulates float32 in double and rounds
/// each product (a float32 running product differs in 991 of the 1000 values).
pub(crate) fn alphas_cumprod_f32(betas: &[f64]) -> Vec<f32> {
    let mut acc = 1.0f64;
    betas
        .iter()
        .map(|&b| {
            acc *= f64::from(1.0 - b as f32);
            acc as f32
        })
        .collect()
}

/// Step i's guidance weight of the Local stage: `min(cap, linspace(r0, r1, steps)[i])`
/// (diffusion.py:507: `np.clip(np.linspace(0, 2w, 50), None, w)`).
pub(crate) fn ramp_weights(ramp: [f32; 2], cap: f32, steps: usize) -> Vec<f32> {
    let (a, b) = (f64::from(ramp[0]), f64::from(ramp[1]));
    (0..steps)
        .map(|i| {
            let t = if steps > 1 {
                a + (b - a) * i as f64 / (steps - 1) as f64
            } else {
                a
            };
            t.min(f64::from(cap)) as f32
        })
        .collect()
}

/// One DDIM update in float32 (diffusion.py:280-293): `x0` clamped to [-1, 1], the noise it
/// implies, then `x0·√ā' + c·ε + σ·z`; at the last step (next = -1) the clamped x0.
pub(crate) fn ddim_update(
    x: &mut [f32],
    model_x0: &[f32],
    alphas: &[f32],
    t: i64,
    next: i64,
    eta: f32,
    noise: Option<&[f32]>,
) {
    let a = alphas[t as usize];
    let recip = (1.0 / a).sqrt();
    let recipm1 = (1.0 / a - 1.0).sqrt();
    if next < 0 {
        for (xi, m) in x.iter_mut().zip(model_x0) {
            *xi = m.clamp(-1.0, 1.0);
        }
        return;
    }
    let an = alphas[next as usize];
    let sigma = eta * ((1.0 - a / an) * (1.0 - an) / (1.0 - a)).sqrt();
    let c = (1.0 - an - sigma * sigma).sqrt();
    let sqrt_an = an.sqrt();
    for (k, (xi, m)) in x.iter_mut().zip(model_x0).enumerate() {
        let x0 = m.clamp(-1.0, 1.0);
        let eps = (recip * *xi - x0) / recipm1;
        let z = noise.map_or(0.0, |n| sigma * n[k]);
        *xi = x0 * sqrt_an + c * eps + z;
    }
}

/// The genre danced when none is given: by the song's tempo, counted from the beat column of
/// the features (column 34, one-hot beats): under 100 BPM "Chinese", 100 up to 125 "Jazz", from
/// 125 "Popping" — each looked up by name in the package, else genre 0.
pub fn default_genre(
    spec: &LodgeSpec<'_>,
    music: ArrayView2<'_, f32>,
    fps: f64,
) -> (usize, String) {
    let beats = music.column(34).iter().filter(|v| **v > 0.5).count();
    let seconds = music.nrows() as f64 / fps;
    let bpm = if seconds > 0.0 {
        beats as f64 * 60.0 / seconds
    } else {
        0.0
    };
    let name = match bpm {
        b if b < 100.0 => "Chinese",
        b if b < 125.0 => "Jazz",
        _ => "Popping",
    };
    let id = spec.genre_id(name).unwrap_or(0);
    (
        id,
        format!(
            "by tempo ({bpm:.0} BPM from the beat column; another can be chosen by name or id)"
        ),
    )
}

/// Dance to `music` (`(T, 35)` fact35 at the package's rate).
pub fn generate_lodge(
    package: &mut ModelPackage,
    music: ArrayView2<'_, f32>,
    options: &LodgeOptions,
    progress: &mut dyn FnMut(LodgeStage, usize, usize),
) -> Result<LodgeDance> {
    let manifest = package.manifest().clone();
    let spec = manifest.lodge_spec()?;
    let l = spec.section;
    let [global_stage, local_stage] = l.stages();
    let input = |what: &str, reason: String| Error::Input {
        what: what.into(),
        reason,
    };
    if music.ncols() != choreo_dsp::FACT35_COLUMNS {
        return Err(input(
            "music features",
            format!("{} columns, fact35 has 35", music.ncols()),
        ));
    }
    if let Some(i) = music.iter().position(|v| !v.is_finite()) {
        return Err(input("music features", format!("value {i} is not finite")));
    }
    let plan = plan(music.nrows(), options.compat)?;
    let (genre, genre_reason) = match &options.genre {
        Some(g) => (
            spec.genre_id(g).ok_or_else(|| {
                input(
                    "genre",
                    format!(
                        "{} is not a genre of {} (ids 0..{}: {})",
                        choreo_dsp::quote(g),
                        manifest.name,
                        l.genres.len(),
                        l.genres.join(", ")
                    ),
                )
            })?,
            "given".to_string(),
        ),
        None => default_genre(&spec, music, manifest.motion.fps),
    };
    let schedule = manifest.schedule()?;
    let alphas = alphas_cumprod_f32(schedule.betas());
    let times = timesteps(&spec, schedule.train_steps(), options.steps);
    let steps = times.len() - 1;
    if steps == 0 || steps > schedule.train_steps() {
        return Err(input(
            "steps",
            format!("must be in 1..={}", schedule.train_steps()),
        ));
    }
    let eta = options.eta.unwrap_or(manifest.sampler.eta);
    let g_count = plan.global_starts.len();
    let l_count = plan.local_starts.len();
    let style_dim = l.local.style_noise;
    if let Some(n) = &options.init_noise {
        let want = [
            (
                "global_xT",
                n.global_x.shape(),
                vec![g_count, l.global.keyframes, LODGE_FEATURES],
            ),
            (
                "local_xT",
                n.local_x.shape(),
                vec![l_count, l.local.frames, LODGE_FEATURES],
            ),
            (
                "local_style",
                n.local_style.shape(),
                vec![steps, 2, l_count, style_dim],
            ),
        ];
        for (name, got, want) in want {
            if got != want.as_slice() {
                return Err(input(
                    "initial noise",
                    format!("{name} is {got:?}; this song, package and step count need {want:?}"),
                ));
            }
        }
    }
    // The music padded with its last frame (the default mode's tail and short songs).
    let mut padded = Array2::<f32>::zeros((plan.music_frames, music.ncols()));
    for (i, mut row) in padded.outer_iter_mut().enumerate() {
        row.assign(&music.row(i.min(music.nrows() - 1)));
    }
    let chunk = options.chunk_windows.max(1);
    let mut stats = LodgeStats {
        global_windows: g_count,
        local_windows: l_count,
        steps,
        frames: plan.out_frames,
        ..LodgeStats::default()
    };
    let sampler = Ddim {
        alphas: &alphas,
        times: &times,
        eta: eta as f32,
    };

    // Global stage.
    let mut global_windows = Array3::<f32>::zeros((g_count, l.global.keyframes, LODGE_FEATURES));
    let global_weights = vec![l.global.guidance; steps];
    let total = g_count.div_ceil(chunk) * steps;
    for (c, first) in (0..g_count).step_by(chunk).enumerate() {
        let ids: Vec<usize> = (first..(first + chunk).min(g_count)).collect();
        let mut x = Array3::<f32>::zeros((ids.len(), l.global.keyframes, LODGE_FEATURES));
        let mut draw = NoiseSource::new(options.seed, 2 * c as u64);
        for (k, &w) in ids.iter().enumerate() {
            match &options.init_noise {
                Some(n) => x
                    .index_axis_mut(Axis(0), k)
                    .assign(&n.global_x.index_axis(Axis(0), w)),
                None => draw.fill(
                    x.index_axis_mut(Axis(0), k)
                        .as_slice_mut()
                        .expect("standard"),
                ),
            }
        }
        let mut windows_music = Array3::<f32>::zeros((ids.len(), l.global.music_frames, 35));
        for (k, &w) in ids.iter().enumerate() {
            let at = plan.global_starts[w];
            windows_music
                .index_axis_mut(Axis(0), k)
                .assign(&padded.slice(s![at..at + l.global.music_frames, ..]));
        }
        let run = StageRun {
            stage: global_stage,
            music: windows_music.view(),
            genre: None,
            weights: &global_weights,
            constraint: None,
        };
        let mut step_noise = NoiseSource::new(options.seed, 2 * c as u64 + 1);
        let done = c * steps;
        let out = run.sample(
            package,
            x,
            &sampler,
            &mut step_noise,
            &mut |_, _, _| Ok(()),
            &mut stats,
            &mut |i| progress(LodgeStage::Global, done + i, total),
        )?;
        for (k, &w) in ids.iter().enumerate() {
            global_windows
                .index_axis_mut(Axis(0), w)
                .assign(&out.index_axis(Axis(0), k));
        }
    }
    let keyframes = raw_frames(global_windows.view(), spec.normalizer);
    let key_rows = keyframe_rows(keyframes.view(), l_count);

    // Local stage.
    let weights = ramp_weights(l.local.guidance_ramp, l.local.guidance, steps);
    let mut local_windows = Array3::<f32>::zeros((l_count, l.local.frames, LODGE_FEATURES));
    let mut local_constraints = LodgeConstraints {
        value: Array3::zeros((l_count, l.local.frames, LODGE_FEATURES)),
        mask: Array3::zeros((l_count, l.local.frames, LODGE_FEATURES)),
    };
    let total = l_count.div_ceil(chunk) * steps;
    let stream0 = 2 * g_count.div_ceil(chunk) as u64;
    for (c, first) in (0..l_count).step_by(chunk).enumerate() {
        let ids: Vec<usize> = (first..(first + chunk).min(l_count)).collect();
        let n = ids.len();
        let mut x = Array3::<f32>::zeros((n, l.local.frames, LODGE_FEATURES));
        let mut draw = NoiseSource::new(options.seed, stream0 + 3 * c as u64);
        let mut windows_music = Array3::<f32>::zeros((n, l.local.frames, 35));
        for (k, &w) in ids.iter().enumerate() {
            match &options.init_noise {
                Some(noise) => x
                    .index_axis_mut(Axis(0), k)
                    .assign(&noise.local_x.index_axis(Axis(0), w)),
                None => draw.fill(
                    x.index_axis_mut(Axis(0), k)
                        .as_slice_mut()
                        .expect("standard"),
                ),
            }
            let cons = local_constraint(
                key_rows[w].view(),
                spec.normalizer,
                l.local.frames,
                options.compat,
            );
            local_constraints
                .value
                .index_axis_mut(Axis(0), w)
                .assign(&cons.value);
            local_constraints
                .mask
                .index_axis_mut(Axis(0), w)
                .assign(&cons.mask);
            let at = plan.local_starts[w];
            windows_music
                .index_axis_mut(Axis(0), k)
                .assign(&padded.slice(s![at..at + l.local.frames, ..]));
        }
        let genres = vec![genre as i64; n];
        let run = StageRun {
            stage: local_stage,
            music: windows_music.view(),
            genre: Some(&genres),
            weights: &weights,
            // This chunk's windows are consecutive: its rows of the whole song's in-painting.
            constraint: Some((
                local_constraints.value.slice(s![first..first + n, .., ..]),
                local_constraints.mask.slice(s![first..first + n, .., ..]),
            )),
        };
        let mut style_draw = NoiseSource::new(options.seed, stream0 + 3 * c as u64 + 2);
        let mut style = |step: usize, rows: usize, out: &mut Array2<f32>| -> Result<()> {
            match &options.init_noise {
                // Rows: the unconditional call's windows, then the conditional call's.
                Some(noise) => {
                    for (half, branch) in [0, 1].into_iter().enumerate() {
                        for (k, &w) in ids.iter().enumerate() {
                            out.row_mut(half * rows + k)
                                .assign(&noise.local_style.slice(s![step, branch, w, ..]));
                        }
                    }
                }
                None => style_draw.fill(out.as_slice_mut().expect("standard")),
            }
            Ok(())
        };
        let mut step_noise = NoiseSource::new(options.seed, stream0 + 3 * c as u64 + 1);
        let done = c * steps;
        let out = run.sample(
            package,
            x,
            &sampler,
            &mut step_noise,
            &mut style,
            &mut stats,
            &mut |i| progress(LodgeStage::Local, done + i, total),
        )?;
        for (k, &w) in ids.iter().enumerate() {
            local_windows
                .index_axis_mut(Axis(0), w)
                .assign(&out.index_axis(Axis(0), k));
        }
    }
    let mut raw = raw_frames(local_windows.view(), spec.normalizer);
    if options.compat == LodgeCompat::Fixed {
        continue_root(&mut raw);
    }
    let flat = raw
        .into_shape_with_order((l_count * l.local.frames, LODGE_FEATURES))
        .map_err(|e| input("windows", e.to_string()))?;
    let features = flat.slice(s![..plan.out_frames, ..]).to_owned();
    Ok(LodgeDance {
        features,
        global_windows,
        local_windows,
        local_constraints,
        genre,
        genre_reason,
        steps,
        eta,
        stats,
    })
}

/// Raw frames of normalised windows: un-normalised, 6D re-orthonormalised (diffusion.py:
/// 940-960 and 1078-1086).
fn raw_frames(windows: ArrayView3<'_, f32>, normalizer: &MinMaxNormalizer) -> Array3<f32> {
    let mut raw = windows.to_owned();
    for mut frame in raw.lanes_mut(Axis(2)) {
        for (c, v) in frame.iter_mut().enumerate() {
            *v = normalizer.unnormalize(c, *v);
        }
        reorthonormalize(frame.as_slice_mut().expect("standard layout"));
    }
    raw
}

/// The default mode's root continuity: each Local window's root x and z shifted so its first
/// frame continues the previous window's last frame at that frame's velocity.
fn continue_root(raw: &mut Array3<f32>) {
    for w in 1..raw.len_of(Axis(0)) {
        let last = raw.len_of(Axis(1)) - 1;
        for c in [ROOT, ROOT + 2] {
            let prev_end = raw[[w - 1, last, c]];
            let velocity = raw[[w - 1, last, c]] - raw[[w - 1, last - 1, c]];
            let shift = prev_end + velocity - raw[[w, 0, c]];
            raw.slice_mut(s![w, .., c]).mapv_inplace(|v| v + shift);
        }
    }
}

/// The DDIM schedule of a run.
struct Ddim<'a> {
    alphas: &'a [f32],
    /// Timesteps followed by -1.
    times: &'a [i64],
    eta: f32,
}

/// One stage's windows of a chunk.
struct StageRun<'a> {
    stage: StageLayout,
    music: ArrayView3<'a, f32>,
    genre: Option<&'a [i64]>,
    weights: &'a [f32],
    constraint: Option<(ArrayView3<'a, f32>, ArrayView3<'a, f32>)>,
}

type StyleFill<'f> = dyn FnMut(usize, usize, &mut Array2<f32>) -> Result<()> + 'f;

impl StageRun<'_> {
    /// The DDIM loop with classifier-free guidance (unconditional rows first, model.py:869-873)
    /// and, with a constraint, in-painting after every step but the last.
    #[allow(clippy::too_many_arguments)]
    fn sample(
        &self,
        package: &mut ModelPackage,
        mut x: Array3<f32>,
        ddim: &Ddim<'_>,
        step_noise: &mut NoiseSource,
        style: &mut StyleFill<'_>,
        stats: &mut LodgeStats,
        progress: &mut dyn FnMut(usize),
    ) -> Result<Array3<f32>> {
        let n = x.len_of(Axis(0));
        let (music_role, denoiser_role) = (self.stage.music, self.stage.denoiser);
        // The music branch once: rows 0..n with the music dropped, n..2n with it kept.
        let doubled = ndarray::concatenate(Axis(0), &[self.music, self.music])
            .map_err(|e| internal(e.to_string()))?;
        let keep: Vec<f32> = (0..2 * n).map(|i| if i < n { 0.0 } else { 1.0 }).collect();
        let mut cond = package.component(music_role)?.run(&[
            ("music", doubled.view().into()),
            ("keep", ndarray::aview1(&keep).into()),
        ])?;
        // Every output of the music branch, by name (`cond_tokens` and `cond_hidden`, or
        // `cond_hidden` and every layer's cross-attention `cross_k`/`cross_v` of the music
        // tokens): the manifest check made them exactly the denoiser's music inputs; the same at
        // every step.
        let music_out = package
            .component(music_role)?
            .spec()
            .outputs
            .iter()
            .map(|spec| Ok((spec.name.clone(), cond.take(&spec.name)?)))
            .collect::<Result<Vec<_>>>()?;
        let genre: Option<Vec<i64>> = self.genre.map(|g| g.iter().chain(g).copied().collect());
        let style_dim = package
            .manifest()
            .lodge
            .as_ref()
            .map_or(0, |l| l.local.style_noise);
        let mut style_rows = Array2::<f32>::zeros((2 * n, style_dim));
        let mut noise = vec![0.0f32; x.len()];
        // Step buffers, filled in place: x twice (unconditional rows, then conditional), the
        // timestep per row, the guided x0.
        let (frames, dim) = (x.len_of(Axis(1)), x.len_of(Axis(2)));
        let mut doubled_x = Array3::<f32>::zeros((2 * n, frames, dim));
        let mut ts = vec![0i64; 2 * n];
        let mut guided = vec![0.0f32; x.len()];
        for (i, pair) in ddim.times.windows(2).enumerate() {
            let (t, next) = (pair[0], pair[1]);
            doubled_x.slice_mut(s![..n, .., ..]).assign(&x);
            doubled_x.slice_mut(s![n.., .., ..]).assign(&x);
            ts.fill(t);
            let mut inputs: Vec<(&str, crate::runtime::component::TensorView<'_>)> = vec![
                ("x_t", doubled_x.view().into()),
                ("t", ndarray::aview1(&ts).into()),
            ];
            inputs.extend(
                music_out
                    .iter()
                    .map(|(name, v)| (name.as_str(), v.view().into())),
            );
            if let Some(g) = &genre {
                style(i, n, &mut style_rows)?;
                inputs.push(("genre", ndarray::aview1(g).into()));
                inputs.push(("style_noise", style_rows.view().into()));
            }
            let out = package.component(denoiser_role)?.run(&inputs)?.take("x0")?;
            stats.evaluations += 1;
            let out = out
                .into_shape_with_order((2, x.len()))
                .map_err(|e| internal(e.to_string()))?;
            let w = self.weights[i];
            for ((g, u), c) in guided.iter_mut().zip(out.row(0)).zip(out.row(1)) {
                *g = u + (c - u) * w;
            }
            let z = if ddim.eta > 0.0 && next >= 0 {
                step_noise.fill(&mut noise);
                Some(noise.as_slice())
            } else {
                None
            };
            let xs = x.as_slice_mut().expect("standard layout");
            ddim_update(xs, &guided, ddim.alphas, t, next, ddim.eta, z);
            if next >= 0
                && let Some((value, mask)) = &self.constraint
            {
                for ((xi, v), m) in x.iter_mut().zip(value.iter()).zip(mask.iter()) {
                    if *m > 0.5 {
                        *xi = *v;
                    }
                }
            }
            progress(i + 1);
        }
        Ok(x)
    }
}

fn internal(reason: String) -> Error {
    Error::Input {
        what: "lodge pipeline".into(),
        reason,
    }
}

#[cfg(test)]
#[path = "lodge_tests.rs"]
mod tests;
