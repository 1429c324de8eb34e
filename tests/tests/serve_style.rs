//! `choreod serve` with `[style]`: motion files dropped into the style inbox are stylized with
//! the configured style reference, with the songs' exactly-one-outcome guarantee; config
//! refusals; a `kill -9` with style jobs in flight.

use std::fs;
use std::time::Duration;

use choreod_tests::daemon::PATIENCE;
use choreod_tests::daemon::{Home, drop_file, wav_bytes};
use choreod_tests::{AISTPP_PKL as PKL, motion_asset, run, text, workspace_root};

const BVH: &str = "cmu_01_01_8s_30fps.bvh";
/// The style reference, copied under a name no content has, so the provenance shows which.
const STYLE: &str = "style-ref.pkl";

fn asset_bytes(name: &str) -> Vec<u8> {
    fs::read(motion_asset(name)).expect("a bundled motion file")
}

fn stem(name: &str) -> String {
    name.rsplit_once('.')
        .map_or(name, |(stem, _)| stem)
        .to_string()
}

/// A home whose `[style]` watches `style-in/` with `style-ref.pkl` (the AIST++ dance) as style.
fn style_home() -> Home {
    let home = Home::new(&format!(
        "[style]\nenabled = true\ninbox = \"style-in\"\nstyle = \"{STYLE}\"\n"
    ));
    fs::create_dir(home.path().join("style-in")).expect("mkdir style-in");
    fs::copy(motion_asset(PKL), home.path().join(STYLE)).expect("copy the style reference");
    home
}

/// `out/<stem>.h5` is the stylization of `content` with the configured style: the same features
/// `choreod stylize` writes for the same inputs (same package defaults, seed 0), and a
/// provenance naming the content and the style reference.
fn assert_stylized(home: &Home, content: &str) {
    let daemon_out = assert_as_the_cli(home, &motion_asset(content), STYLE);
    let p = daemon_out.provenance.expect("provenance");
    assert_eq!(p.source_name, content, "the content is named");
    let style = p.style.expect("style provenance");
    assert_eq!(
        (style.name.as_str(), style.mode.as_str()),
        (STYLE, "transfer"),
        "the configured style reference and mode"
    );
}

/// The daemon's `out/<stem>.h5` of `content` has the features `choreod stylize` writes for
/// `content` with the home's `style` file as it is now; returns the daemon's file.
fn assert_as_the_cli(
    home: &Home,
    content: &std::path::Path,
    style: &str,
) -> choreo_datasets::MotionFile {
    let name = content
        .file_name()
        .and_then(|n| n.to_str())
        .expect("a name");
    let stem = stem(name);
    let daemon_out = choreo_datasets::read_motion_file(&home.out().join(format!("{stem}.h5")))
        .expect("a complete motion file");
    let cli_path = home.path().join(format!("cli-{stem}.h5"));
    let cli = run(&[
        "stylize",
        "--content",
        text(content),
        "--style",
        text(&home.path().join(style)),
        "-o",
        text(&cli_path),
    ]);
    assert!(cli.status.success(), "choreod stylize: {cli:?}");
    let cli = choreo_datasets::read_motion_file(&cli_path).expect("the CLI's motion file");
    let (got, want) = (
        daemon_out.features.as_ref().expect("/motion/features"),
        cli.features.expect("the CLI writes /motion/features"),
    );
    assert_eq!(got.data.ncols(), 263, "HumanML3D features");
    // Same inputs, same options, same seed: the same bytes, so exact equality.
    assert_eq!(got.data, want.data, "{name}: the daemon's job is the CLI's");
    daemon_out
}

#[test]
fn each_dropped_motion_and_song_gets_exactly_one_outcome() {
    let mut home = style_home();
    let style_in = home.path().join("style-in");
    // A song in the style inbox and a motion in the song inbox are not theirs: left alone.
    drop_file(&style_in, "stray.wav", &wav_bytes(1.0, 1));
    drop_file(&home.inbox(), "stray.bvh", &asset_bytes(BVH));
    let mut daemon = home.start();
    home.wait_healthy(&mut daemon);
    for name in [BVH, PKL] {
        drop_file(&style_in, name, &asset_bytes(name));
    }
    // A BVH cut off inside its hierarchy: a hostile input like a truncated song.
    let bvh = asset_bytes(BVH);
    drop_file(&style_in, "cut.bvh", &bvh[..200]);
    drop_file(&home.inbox(), "song.wav", &wav_bytes(1.0, 0));

    daemon.wait_until("four outcomes", PATIENCE, || {
        let (h5, reports) = home.outcomes();
        h5 + reports >= 4 && home.names("state/work").is_empty()
    });
    std::thread::sleep(Duration::from_millis(500)); // a fifth outcome would show by now
    assert_eq!(
        home.names("out"),
        [
            format!("{}.h5", stem(PKL)),
            format!("{}.h5", stem(BVH)),
            "song.h5".into()
        ]
    );
    assert_stylized(&home, BVH);
    assert_stylized(&home, PKL);
    let song = choreo_datasets::read_motion_file(&home.out().join("song.h5")).expect("the dance");
    assert!(
        song.provenance.expect("provenance").style.is_none(),
        "the song was danced, not stylized"
    );

    let failed = home.reports();
    assert_eq!(failed.len(), 1, "{failed:?}");
    let reason = failed[0]["reason"].as_str().expect("a reason");
    assert_eq!(failed[0]["stage"], "stylize");
    assert!(
        reason.contains("cut.bvh") && !reason.contains('\n'),
        "one line naming the file: {reason}"
    );
    assert!(
        home.names("state/failed")
            .iter()
            .any(|n| n.ends_with("__cut.bvh")),
        "the input is kept beside its report"
    );
    let done = home.names("state/done");
    assert_eq!(done.len(), 3, "{done:?}");
    assert_eq!(home.names("style-in"), ["stray.wav"]);
    assert_eq!(home.names("inbox"), ["stray.bvh"]);
    assert_eq!(
        home.metric("choreod_jobs_total{outcome=\"done\"}"),
        Some(3.0)
    );
    assert_eq!(
        home.metric("choreod_job_failures_total{stage=\"stylize\"}"),
        Some(1.0)
    );
    // Encoded once at the start; both style jobs reused it.
    assert_eq!(home.metric("choreod_style_encodings_total"), Some(1.0));
}

/// The style reference is encoded once and reused while its file is unchanged; replaced by
/// another motion (the same name, other content), the next job encodes and uses the new one.
#[test]
fn a_style_file_replaced_while_serving_is_encoded_again_and_used() {
    const STYLE_BVH: &str = "style-ref.bvh";
    let mut home = Home::new(&format!(
        "[style]\nenabled = true\ninbox = \"style-in\"\nstyle = \"{STYLE_BVH}\"\n"
    ));
    let style_in = home.path().join("style-in");
    fs::create_dir(&style_in).expect("mkdir style-in");
    let full = asset_bytes(BVH);
    fs::write(home.path().join(STYLE_BVH), &full).expect("write the style");
    let mut daemon = home.start();
    home.wait_healthy(&mut daemon);
    let encodings = || home.metric("choreod_style_encodings_total");
    assert_eq!(encodings(), Some(1.0), "encoded at the start");

    let job = |name: &str, daemon: &mut choreod_tests::daemon::Daemon| {
        let want = home.outcomes().0 + 1;
        // The CLI stylizes the same content under the same name.
        fs::copy(motion_asset(PKL), home.path().join(name)).expect("copy the content");
        drop_file(&style_in, name, &asset_bytes(PKL));
        daemon.wait_until(name, PATIENCE, || {
            home.outcomes().0 >= want && home.names("state/work").is_empty()
        });
        assert!(home.reports().is_empty(), "{:?}", home.reports());
        let out = assert_as_the_cli(&home, &home.path().join(name), STYLE_BVH);
        out.features.expect("features").data
    };
    let first = job("first.pkl", &mut daemon);
    assert_eq!(encodings(), Some(1.0), "reused for the first job");

    // The first half of the motion: another style, written the way an editor saves (rename).
    let text_bvh = String::from_utf8(full).expect("a BVH is text");
    let (head, motion) = text_bvh.split_once("MOTION").expect("a MOTION section");
    let frames: Vec<&str> = motion.lines().skip(3).collect();
    let half = format!(
        "{head}MOTION\nFrames: {}\n{}\n{}\n",
        frames.len() / 2,
        motion.lines().nth(2).expect("Frame Time line"),
        frames[..frames.len() / 2].join("\n")
    );
    drop_file(home.path(), STYLE_BVH, half.as_bytes());
    let second = job("second.pkl", &mut daemon);
    assert_ne!(first, second, "the new style changed the result");
    assert_eq!(
        encodings(),
        Some(2.0),
        "encoded again once the file changed"
    );
    let third = job("third.pkl", &mut daemon);
    assert_eq!(third, second, "the same content and style: the same result");
    assert_eq!(encodings(), Some(2.0), "the new style reused");
    let style_sha256 = |out: &str| {
        let m = choreo_datasets::read_motion_file(&home.out().join(out)).expect("motion file");
        m.provenance
            .and_then(|p| p.style)
            .expect("style provenance")
            .sha256
    };
    let now = choreo_datasets::sha256_file(&home.path().join(STYLE_BVH)).expect("hash");
    assert_eq!(
        style_sha256("third.h5"),
        now,
        "the provenance names the new style"
    );
    assert_ne!(
        style_sha256("first.h5"),
        now,
        "and the first job the old one"
    );
}

#[test]
fn style_jobs_claimed_before_a_kill_9_finish_exactly_once_as_style_jobs() {
    let mut home = style_home();
    let style_in = home.path().join("style-in");
    let mut daemon = home.start();
    home.wait_healthy(&mut daemon);
    for i in 0..4 {
        drop_file(&style_in, &format!("walk{i}.bvh"), &asset_bytes(BVH));
    }
    // Killed once the first claim is durable: the claimed jobs (running or queued) must come
    // back as style jobs from their records, not be taken for songs.
    daemon.wait_until("a claimed style job", PATIENCE, || {
        !home.names("state/work").is_empty()
    });
    daemon.kill9();
    let mut daemon = home.start();
    daemon.wait_until("four outcomes", PATIENCE, || {
        let (h5, reports) = home.outcomes();
        h5 + reports >= 4
            && home.names("state/work").is_empty()
            && home.names("style-in").is_empty()
    });
    std::thread::sleep(Duration::from_millis(500));
    assert_eq!(
        home.names("out"),
        ["walk0.h5", "walk1.h5", "walk2.h5", "walk3.h5"],
        "one output each, none twice; log:\n{}",
        daemon.log_text()
    );
    assert!(home.reports().is_empty(), "{:?}", home.reports());
    for i in 0..4 {
        let m = choreo_datasets::read_motion_file(&home.out().join(format!("walk{i}.h5")))
            .expect("a complete motion file");
        let style = m
            .provenance
            .and_then(|p| p.style)
            .expect("style provenance");
        assert_eq!(style.name, STYLE);
    }
}

#[test]
fn check_config_refuses_an_overlapping_style_inbox_and_a_missing_style_file() {
    let home = Home::new("");
    fs::write(home.path().join("s.bvh"), asset_bytes(BVH)).expect("write the style");
    let config = home.config();
    let base = fs::read_to_string(&config).expect("the home's config");
    for (section, key, why) in [
        (
            "[style]\nenabled = true\ninbox = \"inbox\"\nstyle = \"s.bvh\"\n",
            "`style.inbox`",
            "the same folder as `paths.inbox`",
        ),
        (
            "[style]\nenabled = true\ninbox = \"inbox/style\"\nstyle = \"s.bvh\"\n",
            "`style.inbox`",
            "inside `paths.inbox`",
        ),
        (
            "[style]\nenabled = true\ninbox = \"si\"\nstyle = \"missing.bvh\"\n",
            "`style.style`",
            "not a file",
        ),
    ] {
        fs::create_dir_all(home.path().join("inbox/style")).expect("mkdir");
        fs::create_dir_all(home.path().join("si")).expect("mkdir");
        fs::write(&config, format!("{base}\n{section}")).expect("write the config");
        let out = run(&["check-config", text(&config)]);
        let err = String::from_utf8_lossy(&out.stderr);
        assert_eq!(out.status.code(), Some(3), "{section}: {err}");
        assert!(err.contains(key) && err.contains(why), "{section}: {err}");
        fs::remove_dir(home.path().join("inbox/style")).expect("rmdir");
    }
}

#[test]
fn serve_refuses_to_start_when_the_style_reference_or_package_cannot_be_used() {
    let exemplar = workspace_root().join("models/packages/exemplar");
    for (style, model, why) in [
        // Passes preflight (a file), but the style package cannot read it.
        ("cut.bvh", None, "style.style: "),
        // A model package, but a dance one.
        (STYLE, Some(&exemplar), "needs a style-transfer package"),
    ] {
        let model = model.map_or(String::new(), |m| format!("model = \"{}\"\n", text(m)));
        let mut home = Home::new(&format!(
            "[style]\nenabled = true\ninbox = \"style-in\"\nstyle = \"{style}\"\n{model}"
        ));
        fs::create_dir(home.path().join("style-in")).expect("mkdir style-in");
        fs::copy(motion_asset(PKL), home.path().join(STYLE)).expect("copy the style");
        fs::write(home.path().join("cut.bvh"), &asset_bytes(BVH)[..200]).expect("write");
        let mut daemon = home.start();
        let status = daemon.wait_exit(PATIENCE).expect("serve exits");
        let log = daemon.log_text();
        assert_eq!(status.code(), Some(4), "{why}: {log}");
        let line = log
            .lines()
            .find(|l| l.starts_with("choreod: error:"))
            .expect("one error line");
        assert!(line.contains(why), "{line}");
    }
}

#[test]
fn serve_refuses_a_style_package_as_the_song_model() {
    let style_gaussian = workspace_root().join("models/packages/style-gaussian");
    let mut home = Home::new(&format!(
        "[runtime]\ndefault_model = \"{}\"\n",
        text(&style_gaussian)
    ));
    let mut daemon = home.start();
    let status = daemon.wait_exit(PATIENCE).expect("serve exits");
    let log = daemon.log_text();
    assert_eq!(status.code(), Some(4), "{log}");
    let line = log
        .lines()
        .find(|l| l.starts_with("choreod: error:"))
        .expect("one error line");
    assert!(
        line.contains("style-gaussian") && line.contains("needs a music-to-dance package"),
        "{line}"
    );
}

#[test]
fn a_style_job_resumed_without_style_enabled_fails_with_the_reason() {
    // As a run with [style] enabled leaves it in the spool: a claimed motion and its record.
    let mut home = Home::new("");
    let job = home.state().join("work/1-0000");
    fs::create_dir_all(&job).expect("mkdir job");
    fs::write(job.join("walk.bvh"), asset_bytes(BVH)).expect("write the input");
    fs::write(
        job.join("job.json"),
        r#"{"id":"1-0000","kind":"stylize","name":"walk.bvh","output":"walk.h5","attempts":0}"#,
    )
    .expect("write the record");
    let mut daemon = home.start();
    daemon.wait_until("the job's outcome", PATIENCE, || {
        home.names("state/work").is_empty()
    });
    let r = home.reports();
    assert_eq!(r.len(), 1, "{r:?}");
    assert_eq!(r[0]["stage"], "stylize");
    let reason = r[0]["reason"].as_str().expect("a reason");
    assert!(
        reason.contains("walk.bvh") && reason.contains("[style] is not enabled"),
        "{reason}"
    );
    assert!(home.names("out").is_empty(), "not danced as a song");
}
