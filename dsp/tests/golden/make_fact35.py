#!/usr/bin/env python3
"""Golden fixtures for choreo-dsp's `fact35` music features (issue 22).

Run locally, never in CI, once per reference environment (both outside the repository):

    python3 -m venv ref07 && ref07/bin/pip install librosa==0.7.2 resampy==0.3.1 \
        numba==0.57.1 numpy==1.23.5 scipy==1.10.1 scikit-learn==1.2.2 soundfile
    python3 -m venv ref010 && ref010/bin/pip install librosa==0.10.1 soundfile
    ref010/bin/python make_fact35.py clips SHARED_FIXTURES_AUDIO   # writes the input clips once
    ref07/bin/python  make_fact35.py golden                        # writes *_lr07.npz
    ref010/bin/python make_fact35.py golden                        # writes *_lr010.npz

`clips` cuts short excerpts of the shared fixture audio (licences: see README.md beside this
script) to 16-bit FLAC, which both libsndfile and symphonia decode to identical samples, and
synthesises a click track. `golden` runs the dance-feature recipe of LODGE
(`dld/data/utils/audio.py` `extract`) / FineDance (`data/code/pre_music.py`) / EDGE
(`baseline_features.py`) with the librosa it runs under, at 30 and 60 fps, and saves every
stage so that each piece of choreo-dsp can be tested alone.

librosa 0.7.2 imports on Python 3.11 / numpy 1.23 with four shims (applied below before the
import): numpy's removed aliases np.int / np.float / np.complex, the module numba.decorators,
and scipy.signal.hann (moved to scipy.signal.windows).
"""
import sys
import types
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
HOP = 512
FPS = (30, 60)


def shim_librosa_07():
    for name, t in (("int", int), ("float", float), ("complex", complex)):
        if name not in np.__dict__:
            setattr(np, name, t)
    import numba

    if "numba.decorators" not in sys.modules:
        mod = types.ModuleType("numba.decorators")
        mod.jit = numba.jit
        sys.modules["numba.decorators"] = mod
    import scipy.signal
    import scipy.signal.windows

    if not hasattr(scipy.signal, "hann"):
        scipy.signal.hann = scipy.signal.windows.hann


# name: (source file, offset s, duration s, mono?)
CLIPS = {
    "beat_vibe_ace": ("vibe_ace_44k_stereo.ogg", 20.0, 4.0, False),
    "rubato_hungarian": ("hungarian_dance_5_44k_stereo.ogg", 2.0, 4.0, True),
}
# AIST++-style name: the fifth field mBR4 gives start_bpm 120 by the LODGE/EDGE rule.
CLICK = "click_sFM_cAll_d00_mBR4_ch00"
# Whole songs: only the onset envelope, peaks, tempo and beats (tests of the tracker alone).
LONG = {"long_vibe_ace": "vibe_ace_44k_stereo.ogg", "long_hungarian": "hungarian_dance_5_44k_stereo.ogg"}


def make_clips(audio_dir):
    import soundfile as sf

    out = HERE / "fact35"
    out.mkdir(exist_ok=True)
    for name, (src, off, dur, mono) in CLIPS.items():
        y, sr = sf.read(str(Path(audio_dir) / src), dtype="float64", always_2d=True)
        y = y[int(off * sr) : int((off + dur) * sr)]
        if mono:
            y = y.mean(axis=1)
        sf.write(str(out / f"{name}.flac"), y, sr, subtype="PCM_16")
    # Click track at 22050 Hz (an upsampling input for 60 fps): 120 BPM 5 ms 1 kHz bursts with
    # an accent every fourth beat, over a quiet tone 30 cents above A4 (a non-zero tuning).
    sr = 22050
    t = np.arange(int(4.0 * sr)) / sr
    y = 0.05 * np.sin(2 * np.pi * 440.0 * 2 ** (0.3 / 12) * t)
    for k, start in enumerate(np.arange(0.1, 4.0, 0.5)):
        i = int(start * sr)
        n = int(0.005 * sr)
        amp = 0.8 if k % 4 == 0 else 0.5
        y[i : i + n] += amp * np.sin(2 * np.pi * 1000.0 * np.arange(n) / sr) * np.hanning(n)
    sf.write(str(out / f"{CLICK}.flac"), y, sr, subtype="PCM_16")


def aist_bpm(stem):
    """LODGE/EDGE `_get_tempo`: the fifth `_` field, e.g. mBR0 -> 80; None otherwise."""
    try:
        f = stem.split("_")[4]
        assert len(f) == 4
        if f[:3] in ["mBR", "mPO", "mLO", "mMH", "mLH", "mWA", "mKR", "mJS", "mJB"]:
            return int(f[3]) * 10 + 80
        if f[:3] == "mHO":
            return int(f[3]) * 5 + 110
    except Exception:
        return None
    return None


def golden(audio_dir):
    import librosa

    v07 = librosa.__version__.startswith("0.7")
    tag = "lr07" if v07 else "lr010"

    out = HERE / "fact35"
    paths = {name: out / f"{name}.flac" for name in list(CLIPS) + [CLICK]}
    for name, path in paths.items():
        for fps in FPS:
            sr = fps * HOP
            d = {}
            y, _ = librosa.load(str(path), sr=sr)
            d["y"] = y
            env = librosa.onset.onset_strength(y=y, sr=sr)
            d["onset_env"] = env
            mel_db = librosa.power_to_db(librosa.feature.melspectrogram(y=y, sr=sr))
            d["mfcc"] = librosa.feature.mfcc(y=y, sr=sr, n_mfcc=20)
            bpo = 12 if v07 else 36
            tuning = librosa.estimate_tuning(y=y, sr=sr, bins_per_octave=bpo)
            d["tuning"] = np.float64(tuning)
            C = np.abs(librosa.cqt(y, sr=sr, hop_length=HOP, n_bins=7 * bpo, bins_per_octave=bpo, tuning=tuning))
            if fps == 30:
                # float64 as librosa holds it: chroma_cens quantises at fixed steps, and float32
                # rounding could move a value across one.
                d["cqt_mag"] = C
            d["chroma_cens"] = librosa.feature.chroma_cens(y=y, sr=sr, hop_length=HOP, n_chroma=12)
            d["peaks"] = librosa.onset.onset_detect(onset_envelope=env.flatten(), sr=sr, hop_length=HOP)
            bpm = aist_bpm(name)
            if bpm is None:
                y22 = librosa.load(str(path))[0]
                d["y22_len"] = np.int64(len(y22))
                d["env22"] = librosa.onset.onset_strength(y=y22, sr=22050)
                bpm = librosa.beat.tempo(y=y22)[0]
            d["start_bpm"] = np.float64(bpm)
            tempo, beats = librosa.beat.beat_track(onset_envelope=env, sr=sr, hop_length=HOP, start_bpm=bpm, tightness=100)
            d["tempo"] = np.float64(tempo)
            d["beats"] = beats
            peak = np.zeros_like(env, dtype=np.float32)
            peak[d["peaks"]] = 1.0
            beat = np.zeros_like(env, dtype=np.float32)
            beat[beats] = 1.0
            feats = np.concatenate(
                [env[:, None], d["mfcc"].T, d["chroma_cens"].T, peak[:, None], beat[:, None]], axis=-1
            )
            d["features"] = feats.astype(np.float32)
            if fps != 30:
                # The 30 fps signal is kept whole (pieces are fed the reference's own signal);
                # at 60 fps only its ends, enough to test the resampler's edges and interior.
                d["y_head"], d["y_tail"] = y[:4096], y[-4096:]
                del d["y"]
            np.savez_compressed(out / f"{name}_{fps}_{tag}.npz", **d)
            print(name, fps, tag, feats.shape, "tuning", tuning, "bpm", bpm, "tempo", tempo, "beats", len(beats), "peaks", len(d["peaks"]))
    # The resampler alone: both filters, down and up, on a stretch of real music.
    if v07:
        import resampy

        x, sr0 = librosa.load(str(paths["beat_vibe_ace"]), sr=None, duration=0.5)
        np.savez_compressed(
            out / "resampy_lr07.npz",
            x=x[: sr0 // 4],
            sr=np.int64(sr0),
            best_15360=resampy.resample(x[: sr0 // 4], sr0, 15360, filter="kaiser_best"),
            best_48000=resampy.resample(x[: sr0 // 4], sr0, 48000, filter="kaiser_best"),
            fast_half=resampy.resample(x[: sr0 // 4], 2, 1, filter="kaiser_fast"),
        )
    # Whole songs: envelope, peaks, tempo, beats at 30 fps.
    for name, src in LONG.items():
        sr = 30 * HOP
        y, _ = librosa.load(str(Path(audio_dir) / src), sr=sr)
        env = librosa.onset.onset_strength(y=y, sr=sr)
        peaks = librosa.onset.onset_detect(onset_envelope=env.flatten(), sr=sr, hop_length=HOP)
        out_d = {"onset_env": env, "peaks": peaks}
        for bpm in (120.0, 95.0):
            tempo, beats = librosa.beat.beat_track(onset_envelope=env, sr=sr, hop_length=HOP, start_bpm=bpm, tightness=100)
            out_d[f"tempo_{int(bpm)}"] = np.float64(tempo)
            out_d[f"beats_{int(bpm)}"] = beats
        np.savez_compressed(out / f"{name}_30_{tag}.npz", **out_d)
        print(name, len(env), "peaks", len(peaks))


if __name__ == "__main__":
    import importlib.util

    if importlib.util.find_spec("librosa") and __import__("importlib.metadata").metadata.version("librosa").startswith("0.7"):
        shim_librosa_07()
    cmd = sys.argv[1]
    audio = sys.argv[2] if len(sys.argv) > 2 else str(HERE.parents[2] / ".." / "shared" / "fixtures" / "audio")
    {"clips": make_clips, "golden": golden}[cmd](audio)
