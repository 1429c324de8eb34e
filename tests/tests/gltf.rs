//! glTF output and the viewer, checked by real clients: the Khronos glTF validator (npm
//! gltf-validator), Blender's glTF importer (background mode), three.js in headless Chromium,
//! and the player's audio element. Also: every verb that writes motion writes the format its
//! output's extension names, or refuses it with the way to get what was meant.
//!
//! Needs `node` with daemon/assets/viewer's npm packages, `blender` and `chromium`
//! (scripts/setup installs all three).
// Helpers outside #[test] functions unwrap too: a failed step is a failed test.
#![allow(clippy::unwrap_used)]

use std::io::{BufRead, BufReader};
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::Duration;

use choreod_tests::browser::Browser;
use choreod_tests::{choreod, one_error_line, run, stderr, workspace_root};
use ndarray::Array3;

fn assets(rel: &str) -> String {
    workspace_root()
        .join("daemon/assets")
        .join(rel)
        .to_string_lossy()
        .into_owned()
}

const PKL: &str = "motion/aistpp_gBR_sBM_cAll_d04_mBR0_ch01.pkl";
const CMU: &str = "motion/cmu_01_01_8s_30fps.bvh";
const SONG: &str = "audio/vibe_ace_44k_stereo.ogg";

fn s(p: &Path) -> String {
    p.to_string_lossy().into_owned()
}

fn ok(args: &[&str]) -> String {
    let out = run(args);
    assert!(out.status.success(), "choreod {args:?}: {}", stderr(&out));
    stderr(&out)
}

fn joints(path: &Path) -> Array3<f32> {
    choreo_datasets::read_npy(path)
        .unwrap()
        .into_dimensionality()
        .unwrap()
}

/// The validator's report on each file: one JSON object per file.
fn validate(files: &[&Path]) -> Vec<serde_json::Value> {
    let out = Command::new("node")
        .arg(workspace_root().join("tests/tools/gltf_validate.mjs"))
        .args(files)
        .output()
        .expect("node installed (scripts/setup)");
    assert!(
        out.status.success(),
        "gltf-validator: {}",
        String::from_utf8_lossy(&out.stderr)
    );
    String::from_utf8_lossy(&out.stdout)
        .lines()
        .map(|l| serde_json::from_str(l).unwrap())
        .collect()
}

/// Motion files of the bundled AIST++ clip (SMPL-24, 60 fps, rigid: SMPL forward kinematics)
/// and CMU clip (31 joints, 30 fps), as glTF in each variant, with their joints as `.npy`.
struct Files {
    dir: tempfile::TempDir,
}

impl Files {
    fn new() -> Files {
        let dir = tempfile::tempdir().unwrap();
        let p = |n: &str| s(&dir.path().join(n));
        for (input, stem) in [(assets(PKL), "aist"), (assets(CMU), "cmu")] {
            ok(&["convert", &input, "-o", &p(&format!("{stem}.npy"))]);
            ok(&["convert", &input, "-o", &p(&format!("{stem}.h5"))]);
            ok(&["convert", &input, "-o", &p(&format!("{stem}.glb"))]);
        }
        ok(&[
            "convert",
            &assets(PKL),
            "-o",
            &p("aist-mixamo.glb"),
            "--rig",
            "mixamo",
        ]);
        ok(&["convert", &assets(CMU), "-o", &p("cmu.gltf")]);
        ok(&[
            "convert",
            &assets(CMU),
            "-o",
            &p("cmu-bones.glb"),
            "--no-mesh",
        ]);
        // HumanML3D features (t2m-22 joints) to glTF, with Mixamo names.
        ok(&[
            "convert",
            &assets(PKL),
            "--to",
            "features",
            "-o",
            &p("t2m.npy"),
        ]);
        ok(&[
            "convert",
            &p("t2m.npy"),
            "-o",
            &p("t2m-mixamo.gltf"),
            "--rig",
            "mixamo",
        ]);
        Files { dir }
    }

    fn path(&self, name: &str) -> PathBuf {
        self.dir.path().join(name)
    }
}

#[test]
fn the_khronos_validator_finds_no_error_or_warning_in_any_gltf_choreod_writes() {
    let files = Files::new();
    let names = [
        "aist.glb",
        "cmu.glb",
        "aist-mixamo.glb",
        "cmu.gltf",
        "cmu-bones.glb",
        "t2m-mixamo.gltf",
    ];
    let paths: Vec<PathBuf> = names.iter().map(|n| files.path(n)).collect();
    // A broken file, to show the harness reports what it finds: the GLB cut in half.
    let broken = files.path("broken.glb");
    let bytes = std::fs::read(&paths[0]).unwrap();
    std::fs::write(&broken, &bytes[..bytes.len() / 2]).unwrap();
    let mut all: Vec<&Path> = paths.iter().map(PathBuf::as_path).collect();
    all.push(&broken);
    let reports = validate(&all);
    for (name, r) in names.iter().zip(&reports) {
        assert_eq!(r["errors"], 0, "{name}: {r}");
        assert_eq!(r["warnings"], 0, "{name}: {r}");
        assert_eq!(r["info"]["animationCount"], 1, "{name}: {r}");
        let skinned = *name != "cmu-bones.glb";
        assert_eq!(r["info"]["hasSkins"], skinned, "{name}: {r}");
        assert_eq!(
            r["info"]["drawCallCount"],
            if skinned { 3 } else { 0 },
            "{name}"
        );
    }
    assert!(reports[6]["errors"].as_u64().unwrap() > 0, "{}", reports[6]);
}

#[test]
fn mixamo_names_need_a_named_skeleton_and_only_formats_with_bones_take_rig_or_mesh_flags() {
    let dir = tempfile::tempdir().unwrap();
    let out = s(&dir.path().join("x.glb"));
    let e = one_error_line(&run(&[
        "convert",
        &assets(CMU),
        "-o",
        &out,
        "--rig",
        "mixamo",
    ]));
    assert!(
        e.contains("--rig mixamo") && e.contains("--rig native"),
        "{e}"
    );
    let h5 = s(&dir.path().join("x.h5"));
    let e = one_error_line(&run(&[
        "convert",
        &assets(PKL),
        "-o",
        &h5,
        "--rig",
        "mixamo",
    ]));
    assert!(e.contains(".bvh, .glb and .gltf"), "{e}");
    let e = one_error_line(&run(&["convert", &assets(PKL), "-o", &h5, "--no-mesh"]));
    assert!(e.contains("--no-mesh"), "{e}");
    assert!(!dir.path().join("x.glb").exists() && !dir.path().join("x.h5").exists());
    // A Mixamo BVH reads back (its names are the Mixamo rig's) to the same joints.
    let bvh = s(&dir.path().join("m.bvh"));
    ok(&["convert", &assets(PKL), "-o", &bvh, "--rig", "mixamo"]);
    let text = std::fs::read_to_string(&bvh).unwrap();
    assert!(
        text.contains("ROOT mixamorig:Hips") && text.contains("JOINT mixamorig:LeftHandMiddle1")
    );
    let (a, b) = (dir.path().join("a.npy"), dir.path().join("b.npy"));
    ok(&["convert", &assets(PKL), "-o", &s(&a)]);
    ok(&["convert", &bvh, "-o", &s(&b)]);
    let (a, b) = (joints(&a), joints(&b));
    // Read back, the joints come in the file's (depth-first) order: SMPL joint of each.
    let order: Vec<usize> = bvh_joint_names(&text)
        .iter()
        .map(|n| {
            let bare = n.strip_prefix("mixamorig:").unwrap();
            choreo_datasets::MIXAMO_NAMES
                .iter()
                .position(|m| *m == bare)
                .unwrap()
        })
        .collect();
    assert_eq!(order.len(), 24);
    let mut worst = 0.0f32;
    for (j, &k) in order.iter().enumerate() {
        for f in 0..a.shape()[0] {
            for c in 0..3 {
                worst = worst.max((a[[f, k, c]] - b[[f, j, c]]).abs());
            }
        }
    }
    // 6-decimal BVH text and the rigid fit of SMPL FK: 1e-4 m, as for the native BVH.
    assert!(worst < 1e-4, "{worst} m");
}

/// The joint names of a BVH hierarchy, in file order.
fn bvh_joint_names(text: &str) -> Vec<String> {
    let mut names = Vec::new();
    let mut words = text.split_whitespace();
    while let Some(w) = words.next() {
        if w == "ROOT" || w == "JOINT" {
            names.push(words.next().unwrap().to_owned());
        }
    }
    names
}

/// Blender (Debian's, background mode) imports the files: one armature with the motion's
/// bones, the action's frame range and rate, bone heads where choreod's joints are, and the
/// mannequin bound to the armature.
#[test]
fn blender_imports_the_glb_bones_animation_and_bound_mesh() {
    let files = Files::new();
    // The names choreod gives SMPL-24 joints: its own skeleton table.
    let smpl = choreo_datasets::SkeletonKind::Smpl24.joint_names();
    let mixamo: Vec<String> = choreo_datasets::MIXAMO_NAMES
        .iter()
        .map(|n| format!("mixamorig:{n}"))
        .collect();
    let cmu_names = bvh_joint_names(&std::fs::read_to_string(assets(CMU)).unwrap());
    // (glb, joints .npy, fps, bone names in joint order)
    let cases = [
        ("aist.glb", "aist.npy", 60.0, smpl.clone()),
        ("aist-mixamo.glb", "aist.npy", 60.0, mixamo),
        ("cmu.glb", "cmu.npy", 30.0, cmu_names),
    ];
    let mut jobs = Vec::new();
    for (glb, npy, fps, bones) in &cases {
        let t = joints(&files.path(npy)).shape()[0];
        jobs.push(serde_json::json!({"file": s(&files.path(glb)), "fps": fps,
            "frames": [0, t / 3, 2 * t / 3, t - 1], "bones": bones}));
    }
    let jobs_path = files.path("jobs.json");
    std::fs::write(&jobs_path, serde_json::to_string(&jobs).unwrap()).unwrap();
    let out_path = files.path("blender.json");
    let out = Command::new("blender")
        .args(["-b", "--factory-startup", "--python"])
        .arg(workspace_root().join("tests/py/blender_gltf.py"))
        .arg("--")
        .args([&jobs_path, &out_path])
        .output()
        .expect("blender installed (scripts/setup)");
    let text = std::fs::read_to_string(&out_path).unwrap_or_else(|_| {
        panic!(
            "blender wrote nothing: {}{}",
            String::from_utf8_lossy(&out.stdout),
            String::from_utf8_lossy(&out.stderr)
        )
    });
    let results: Vec<serde_json::Value> = serde_json::from_str(&text).unwrap();
    for ((glb, npy, fps, bones), r) in cases.iter().zip(&results) {
        assert_eq!(r["armatures"], 1, "{glb}");
        let mut got: Vec<String> = serde_json::from_value(r["bones"].clone()).unwrap();
        let mut want = bones.clone();
        got.sort();
        want.sort();
        assert_eq!(got, want, "{glb}: bones");
        let reference = joints(&files.path(npy));
        let t = reference.shape()[0] as f64;
        let range = r["frame_range"].as_array().unwrap();
        let (first, last) = (range[0].as_f64().unwrap(), range[1].as_f64().unwrap());
        assert!(
            (last - first - (t - 1.0)).abs() < 1e-3,
            "{glb}: frame range {range:?} for {t} frames"
        );
        assert!((r["fps"].as_f64().unwrap() - fps).abs() < 1e-6, "{glb}");
        let mut worst = 0.0f64;
        for (frame, heads) in r["heads"].as_object().unwrap() {
            let f: usize = frame.parse().unwrap();
            for (j, h) in heads.as_array().unwrap().iter().enumerate() {
                for c in 0..3 {
                    let d = h[c].as_f64().unwrap() - f64::from(reference[[f, j, c]]);
                    worst = worst.max(d.abs());
                }
            }
        }
        // The requirement: 1 mm. (Measured: micrometres, float precision through Blender's
        // matrices; the rigid fit of these rigid motions moves no joint.)
        assert!(
            worst < 1e-3,
            "{glb}: a bone head is {worst} m from choreod's joint"
        );
        let meshes = r["meshes"].as_array().unwrap();
        assert_eq!(meshes.len(), 1, "{glb}: {meshes:?}");
        let groups = meshes[0]["groups"].as_object().unwrap();
        assert_eq!(meshes[0]["armature_modifier"], true, "{glb}");
        let bound = groups.values().filter(|n| n.as_u64() > Some(0)).count();
        if *npy == "aist.npy" {
            // Every SMPL joint carries a capsule (its bone to a child, or a stub at a leaf).
            assert_eq!(bound, 24, "{glb}: {groups:?}");
        } else {
            assert!(bound >= 20, "{glb}: {groups:?}");
        }
    }
}

/// `choreod view FILE [extra]`, returning the child and its URL.
fn view(file: &Path, extra: &[&str]) -> (Child, String) {
    let mut child = choreod()
        .arg("view")
        .arg(file)
        .args(extra)
        .stdout(Stdio::piped())
        .stderr(Stdio::null())
        .spawn()
        .unwrap();
    let mut url = String::new();
    BufReader::new(child.stdout.take().unwrap())
        .read_line(&mut url)
        .unwrap();
    (child, url.trim().to_owned())
}

/// Pixels of the canvas bright or coloured enough to be the mannequin (its grey, blue and red
/// materials, lit), not the background (#16181d) or the floor grid (#4c566a at most), and
/// their centroid.
const FIGURE_JS: &str = r#"(() => { const c = document.getElementById("view");
    const o = document.createElement("canvas"); o.width = c.width; o.height = c.height;
    const x = o.getContext("2d"); x.drawImage(c, 0, 0);
    const d = x.getImageData(0, 0, o.width, o.height).data;
    let n = 0, sx = 0, sy = 0;
    for (let i = 0; i < d.length; i += 4)
        if (Math.max(d[i], d[i + 1], d[i + 2]) > 120) {
            n++; sx += (i / 4) % o.width; sy += Math.floor(i / 4 / o.width); }
    return JSON.stringify({n, x: sx / Math.max(n, 1), y: sy / Math.max(n, 1), w: o.width}); })()"#;

fn figure(browser: &mut Browser) -> serde_json::Value {
    serde_json::from_str(browser.eval(FIGURE_JS).as_str().unwrap()).unwrap()
}

#[test]
fn three_js_draws_the_mannequin_and_plays_its_animation() {
    let files = Files::new();
    let h5 = files.path("aist.h5");
    let (mut child, url) = view(&h5, &[]);
    // Paused at a known time: the mannequin is on the canvas, and at another time elsewhere.
    let mut browser = Browser::open(&format!("{url}?t=2.0"));
    assert!(
        browser.wait_for(
            "window.choreod && window.choreod.ready === true",
            Duration::from_secs(30)
        ),
        "the player did not load: {}",
        browser.eval("document.getElementById('status').textContent")
    );
    std::thread::sleep(Duration::from_millis(300));
    let at2 = figure(&mut browser);
    if let Some(path) = std::env::var_os("CHOREOD_SCREENSHOT") {
        std::fs::write(path, browser.screenshot()).unwrap();
    }
    assert_eq!(
        browser.eval("document.getElementById('frame').textContent"),
        "120"
    );
    assert_eq!(
        browser.eval("document.getElementById('time').textContent"),
        "0:02.00 / 0:11.98"
    );
    // 640x480: a dancer about a third of the height is thousands of pixels; an empty canvas
    // (or the grid alone) has none this bright.
    assert!(
        at2["n"].as_u64().unwrap() > 2000,
        "no mannequin drawn: {at2}"
    );
    browser.eval("window.choreod.seek(9.0)");
    std::thread::sleep(Duration::from_millis(300));
    let at9 = figure(&mut browser);
    assert!(at9["n"].as_u64().unwrap() > 2000, "{at9}");
    // The camera follows the hips, so the pose (not the place) changes what is drawn.
    assert_ne!(
        at2["n"], at9["n"],
        "same picture at 2 s and 9 s: {at2} {at9}"
    );
    drop(browser);
    // Playing: the clock and the frame readout advance on their own.
    let mut browser = Browser::open(&url);
    assert!(browser.wait_for(
        "window.choreod && window.choreod.ready === true",
        Duration::from_secs(30)
    ));
    let t0 = browser.eval("window.choreod.time()").as_f64().unwrap();
    std::thread::sleep(Duration::from_millis(1500));
    let t1 = browser.eval("window.choreod.time()").as_f64().unwrap();
    assert!(t1 - t0 > 0.5, "the animation does not play: {t0} then {t1}");
    drop(browser);
    let _ = child.kill();
    let _ = child.wait();
}

/// The player at `url` paused at 2 s, loaded: its readouts and the figure drawn.
fn paused_at_2s(url: &str) -> serde_json::Value {
    let mut browser = Browser::open(&format!("{url}?t=2.0"));
    assert!(
        browser.wait_for(
            "window.choreod && window.choreod.ready === true",
            Duration::from_secs(30)
        ),
        "the player did not load: {}",
        browser.eval("document.getElementById('status').textContent")
    );
    std::thread::sleep(Duration::from_millis(300));
    let text =
        |b: &mut Browser, id: &str| b.eval(&format!("document.getElementById('{id}').textContent"));
    serde_json::json!({
        "figure": figure(&mut browser),
        "mode": text(&mut browser, "mode"),
        "frame": text(&mut browser, "frame"),
        "frames": text(&mut browser, "frames"),
        "fps": text(&mut browser, "fps"),
        "joints": text(&mut browser, "joints"),
        "time": text(&mut browser, "time"),
    })
}

/// Issue 27: `choreod view` opens a glTF file itself (binary, or text with its buffer
/// embedded) and shows it as it shows the motion it was made from; a glTF that needs other
/// files, or is cut short, is refused in one line.
#[test]
fn view_opens_glb_and_gltf_files_as_the_motion_they_were_made_from() {
    let files = Files::new();
    let mut seen = Vec::new();
    for name in ["aist.h5", "aist.glb", "cmu.gltf"] {
        let (mut child, url) = view(&files.path(name), &[]);
        assert!(url.starts_with("http://127.0.0.1:"), "{name}: {url:?}");
        seen.push(paused_at_2s(&url));
        let _ = child.kill();
        let _ = child.wait();
    }
    let [h5, glb, gltf] = &seen[..] else {
        unreachable!()
    };
    // The GLB is the motion file's own glTF: the same skeleton, frames and picture.
    for key in ["mode", "frame", "frames", "fps", "joints", "time"] {
        assert_eq!(glb[key], h5[key], "{key}: {glb} vs {h5}");
    }
    assert_eq!(glb["frames"], "720", "{glb}");
    assert_eq!(glb["frame"], "120", "{glb}");
    let n = |v: &serde_json::Value| v["figure"]["n"].as_f64().unwrap();
    assert!(n(glb) > 2000.0, "no mannequin: {glb}");
    // The same document drawn twice; a tolerance only for the renderer's rasterisation.
    assert!((n(glb) - n(h5)).abs() <= 0.02 * n(h5), "{glb} vs {h5}");
    // The CMU clip as .gltf text: 31 joints at 30 fps.
    assert_eq!(gltf["joints"], "31", "{gltf}");
    assert_eq!(gltf["fps"], "30", "{gltf}");
    assert_eq!(gltf["frame"], "60", "{gltf}");
    assert!(n(gltf) > 2000.0, "no mannequin: {gltf}");

    // Refused: a .gltf whose buffer is another file (nothing beside the given file is read),
    // and a GLB cut short.
    let text = std::fs::read_to_string(files.path("cmu.gltf")).unwrap();
    let mut doc: serde_json::Value = serde_json::from_str(&text).unwrap();
    doc["buffers"][0]["uri"] = "cmu.bin".into();
    let outside = files.path("outside.gltf");
    std::fs::write(&outside, doc.to_string()).unwrap();
    let bytes = std::fs::read(files.path("aist.glb")).unwrap();
    let cut = files.path("cut.glb");
    std::fs::write(&cut, &bytes[..bytes.len() / 2]).unwrap();
    for (file, says) in [
        (&outside, "refers to the file 'cmu.bin'"),
        (&cut, "the file has"),
    ] {
        let out = run(&["view", &s(file)]);
        assert_eq!(out.status.code(), Some(1), "{}", stderr(&out));
        let line = one_error_line(&out);
        assert!(line.contains(says), "{line}");
    }
}

/// `choreod dance` of the bundled song, copied into `dir` first; the dance is written there.
fn dance_beside_its_song(dir: &Path) -> (PathBuf, PathBuf) {
    let song = dir.join("song.ogg");
    std::fs::copy(assets(SONG), &song).unwrap();
    let h5 = dir.join("dance.h5");
    ok(&["dance", &s(&song), "-o", &s(&h5)]);
    (h5, song)
}

/// `choreod view FILE` with stderr kept: the child, its URL, and a thread that collects stderr.
fn view_logged(file: &Path) -> (Child, String, std::thread::JoinHandle<String>) {
    let mut child = choreod()
        .arg("view")
        .arg(file)
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    let err = child.stderr.take().unwrap();
    let log = std::thread::spawn(move || std::io::read_to_string(err).unwrap_or_default());
    let mut url = String::new();
    BufReader::new(child.stdout.take().unwrap())
        .read_line(&mut url)
        .unwrap();
    (child, url.trim().to_owned(), log)
}

/// Issue 27: without --audio, `view` plays the song a dance's provenance names when it sits
/// beside the dance and its sha256 is the one recorded; another file under that name is not
/// played, and both the log and the page say why.
#[test]
fn view_plays_the_song_the_provenance_names_only_when_its_sha256_matches() {
    let dir = tempfile::tempdir().unwrap();
    let (h5, song) = dance_beside_its_song(dir.path());
    let autoplay = ["--autoplay-policy=no-user-gesture-required", "--mute-audio"];

    let (mut child, url, log) = view_logged(&h5);
    let mut browser = Browser::open_with(&url, &autoplay);
    assert!(browser.wait_for(
        "window.choreod && window.choreod.ready === true",
        Duration::from_secs(30)
    ));
    assert_eq!(
        browser.eval("document.getElementById('mode').textContent"),
        "file with song"
    );
    assert_ne!(
        browser.eval("document.getElementById('song').currentSrc"),
        ""
    );
    let at = |b: &mut Browser| {
        b.eval("document.getElementById('song').currentTime")
            .as_f64()
            .unwrap()
    };
    let a0 = at(&mut browser);
    std::thread::sleep(Duration::from_millis(1500));
    let a1 = at(&mut browser);
    assert!(a1 - a0 > 1.0, "the song does not play: {a0} then {a1}");
    drop(browser);
    let _ = child.kill();
    let _ = child.wait();
    let log = log.join().unwrap();
    assert!(
        log.contains(&format!("viewer: playing with {}", song.display())),
        "{log}"
    );

    // Another song under the same name: not played, and said so.
    let mut other = std::fs::read(&song).unwrap();
    other.extend_from_slice(b"changed");
    std::fs::write(&song, other).unwrap();
    let (mut child, url, log) = view_logged(&h5);
    let mut browser = Browser::open_with(&url, &autoplay);
    assert!(browser.wait_for(
        "window.choreod && window.choreod.ready === true",
        Duration::from_secs(30)
    ));
    assert_eq!(
        browser.eval("document.getElementById('mode').textContent"),
        "file"
    );
    assert_eq!(
        browser.eval("document.getElementById('song').currentSrc"),
        ""
    );
    let status = browser.eval("document.getElementById('status').textContent");
    assert!(
        status.as_str().unwrap().contains("differs from the song"),
        "{status}"
    );
    drop(browser);
    let _ = child.kill();
    let _ = child.wait();
    let log = log.join().unwrap();
    assert!(
        log.contains("viewer: no song:")
            && log.contains("differs from the song the dance was made from (sha256)"),
        "{log}"
    );
}

/// The readout of the player: seconds.
fn readout(browser: &mut Browser) -> f64 {
    let text = browser.eval("document.getElementById('time').textContent");
    let now = text
        .as_str()
        .unwrap()
        .split(" / ")
        .next()
        .unwrap()
        .to_owned();
    let (m, s) = now.split_once(':').unwrap();
    m.parse::<f64>().unwrap() * 60.0 + s.parse::<f64>().unwrap()
}

#[test]
fn the_viewer_plays_the_song_and_its_clock_is_the_songs() {
    let files = Files::new();
    let h5 = files.path("aist.h5");
    let (mut child, url) = view(&h5, &["--audio", &assets(SONG)]);
    let mut browser = Browser::open_with(
        &url,
        &["--autoplay-policy=no-user-gesture-required", "--mute-audio"],
    );
    assert!(browser.wait_for(
        "window.choreod && window.choreod.ready === true",
        Duration::from_secs(30)
    ));
    assert_eq!(
        browser.eval("document.getElementById('mode').textContent"),
        "file with song"
    );
    // The song is the file given: its decoded length, to a sample.
    let decoded = choreo_dsp::decode_file(Path::new(&assets(SONG)), &Default::default()).unwrap();
    let song_s = browser
        .eval("document.getElementById('song').duration")
        .as_f64()
        .unwrap();
    assert!(
        (song_s - decoded.duration_s).abs() < 1e-3,
        "song of {song_s} s, decoded {} s",
        decoded.duration_s
    );
    let sample = |b: &mut Browser| {
        let audio = b
            .eval("document.getElementById('song').currentTime")
            .as_f64()
            .unwrap();
        (audio, readout(b))
    };
    let (a0, r0) = sample(&mut browser);
    std::thread::sleep(Duration::from_millis(1500));
    let (a1, r1) = sample(&mut browser);
    assert!(
        a1 - a0 > 1.0 && a1 - a0 < 2.5,
        "the song does not play: {a0} then {a1}"
    );
    // The readout shows the song's time: within one animation frame of it (a sample is taken
    // between two page frames, 1/60 s at most in a headless browser, plus two decimals).
    for (a, r) in [(a0, r0), (a1, r1)] {
        assert!(
            (a - r).abs() < 0.05,
            "readout {r} s while the song is at {a} s"
        );
    }
    // Pause stops both; a seek moves both.
    browser.eval("window.choreod.pause()");
    browser.eval("window.choreod.seek(5.0)");
    std::thread::sleep(Duration::from_millis(500));
    let (a2, r2) = sample(&mut browser);
    std::thread::sleep(Duration::from_millis(500));
    let (a3, r3) = sample(&mut browser);
    assert!(
        (a2 - 5.0).abs() < 1e-3 && (r2 - 5.0).abs() < 0.01,
        "{a2} {r2}"
    );
    assert_eq!((a2, r2), (a3, r3), "paused but moving");
    assert_eq!(
        browser.eval("document.getElementById('frame').textContent"),
        "300"
    );
    drop(browser);
    let _ = child.kill();
    let _ = child.wait();
}

/// Issue 23, item 5: `dance -o x.bvh` wrote HDF5 under that name and `-o x.gif` printed a hint
/// that failed. Now the extension picks the format, and a picture's extension is refused with
/// a command that works.
#[test]
fn dance_and_stylize_write_the_format_the_extension_names() {
    let dir = tempfile::tempdir().unwrap();
    let p = |n: &str| s(&dir.path().join(n));
    let song = assets(SONG);
    ok(&["dance", &song, "-o", &p("d.bvh")]);
    let bvh = std::fs::read(p("d.bvh")).unwrap();
    assert!(bvh.starts_with(b"HIERARCHY"), "not a BVH: {:?}", &bvh[..8]);
    let err = ok(&["dance", &song, "-o", &p("d.glb")]);
    assert!(std::fs::read(p("d.glb")).unwrap().starts_with(b"glTF"));
    assert!(err.contains("Blender"), "{err}");
    ok(&["dance", &song, "-o", &p("d.npy")]);
    assert_eq!(joints(&dir.path().join("d.npy")).shape()[1..], [24, 3]);
    // The BVH is the dance: read back, it is the .npy's joints as a rigid skeleton.
    ok(&["convert", &p("d.bvh"), "-o", &p("back.npy")]);
    let (a, b) = (
        joints(&dir.path().join("d.npy")),
        joints(&dir.path().join("back.npy")),
    );
    assert_eq!(a.shape(), b.shape());
    let worst = a
        .iter()
        .zip(b.iter())
        .map(|(x, y)| (x - y).abs())
        .fold(0.0, f32::max);
    // Generated motion is not rigid: its nearest rigid pose is within a few cm (README: BVH).
    assert!(worst < 0.1, "{worst} m");
    // A picture: refused before the model runs, with a hint that works.
    let gif = p("d.gif");
    let e = one_error_line(&run(&["dance", &song, "-o", &gif]));
    assert!(!Path::new(&gif).exists());
    let hint = e
        .split('`')
        .nth(1)
        .unwrap_or_else(|| panic!("no command in: {e}"));
    assert!(
        hint.starts_with("choreod render ") && hint.ends_with("d.gif"),
        "{e}"
    );
    let made = e.split("write ").nth(1).unwrap().split(' ').next().unwrap();
    ok(&["dance", &song, "-o", made]);
    let words: Vec<&str> = hint.split(' ').skip(1).collect();
    ok(&words);
    assert!(std::fs::read(&gif).unwrap().starts_with(b"GIF8"));
    let e = one_error_line(&run(&["dance", &song, "-o", &p("d.fbx")]));
    assert!(e.contains(".glb"), "{e}");
    // stylize: the same writer.
    let style = assets(PKL);
    ok(&[
        "stylize",
        "--content",
        &assets(CMU),
        "--style",
        &style,
        "-o",
        &p("s.glb"),
    ]);
    assert!(std::fs::read(p("s.glb")).unwrap().starts_with(b"glTF"));
    let e = one_error_line(&run(&[
        "stylize",
        "--content",
        &assets(CMU),
        "--style",
        &style,
        "-o",
        &p("s.gif"),
    ]));
    assert!(e.contains("choreod render"), "{e}");
    let reports = validate(&[&dir.path().join("d.glb"), &dir.path().join("s.glb")]);
    for r in reports {
        assert_eq!(
            (r["errors"].as_u64(), r["warnings"].as_u64()),
            (Some(0), Some(0)),
            "{r}"
        );
    }
}
