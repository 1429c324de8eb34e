//! `choreod serve` refusing to start: a bad config, a spool in use, inbox and state on two
//! filesystems, and the other start-up refusals with their exit codes (3: the config or the
//! folders; 4: the model package or the environment).
//!
//! Needs the binary: `cargo build --release -p choreod` first.

use std::path::Path;
use std::time::Duration;

use choreod_tests::daemon::{Home, exit_code};

#[test]
fn inbox_and_state_on_two_filesystems_is_refused_with_exit_3() {
    let Ok(shm) = tempfile::tempdir_in("/dev/shm") else {
        eprintln!("skipped: no /dev/shm here to put the state folder on another filesystem");
        return;
    };
    let dev = |p: &Path| std::os::unix::fs::MetadataExt::dev(&std::fs::metadata(p).unwrap());
    let mut home = Home::with_paths("", "inbox", &shm.path().display().to_string());
    if dev(&home.inbox()) == dev(shm.path()) {
        eprintln!("skipped: /dev/shm and the temporary folder share a filesystem here");
        return;
    }
    let check = choreod_tests::choreod()
        .arg("check-config")
        .arg(home.config())
        .output()
        .unwrap();
    let stderr = String::from_utf8_lossy(&check.stderr);
    assert_eq!(check.status.code(), Some(3), "{stderr}");
    assert!(
        stderr.contains("paths.state") && stderr.contains("cannot cross filesystems"),
        "{stderr}"
    );
    assert_eq!(stderr.lines().count(), 1, "one line: {stderr}");
    let mut daemon = home.start();
    assert_eq!(exit_code(&mut daemon), 3, "{}", daemon.log_text());
    assert!(daemon.log_text().contains("cannot cross filesystems"));
}

#[test]
fn startup_refusals_exit_3_or_4() {
    let mut home = Home::new("");
    // Overlapping folders and a model directory that is not a package: configuration, exit 3.
    for (extra, needle) in [
        (
            "[paths]\ninbox = \"in\"\noutput = \"in\"\nstate = \"st\"\n",
            "the same folder as `paths.inbox`",
        ),
        (
            "[paths]\ninbox = \"in\"\noutput = \"out\"\nstate = \"in/st\"\n",
            "inside `paths.inbox`",
        ),
        (
            "[paths]\ninbox = \"in\"\noutput = \"out\"\nstate = \"st\"\n[runtime]\ndefault_model = \"nowhere\"\n",
            "runtime.default_model",
        ),
        (
            "[paths]\ninbox = \"in\"\noutput = \"out\"\nstate = \"st\"\n[log]\nlevel = \"verbose\"\n",
            "log.level",
        ),
    ] {
        for d in ["in/st", "out", "st"] {
            std::fs::create_dir_all(home.path().join(d)).unwrap();
        }
        let file = home.path().join("bad.toml");
        std::fs::write(&file, extra).unwrap();
        let out = choreod_tests::choreod()
            .arg("check-config")
            .arg(&file)
            .output()
            .unwrap();
        let stderr = String::from_utf8_lossy(&out.stderr);
        assert_eq!(out.status.code(), Some(3), "{extra}: {stderr}");
        assert!(stderr.contains(needle), "{extra}: {stderr}");
    }

    // The metrics port taken by another process: the environment, exit 4.
    let squatter = std::net::TcpListener::bind(("127.0.0.1", home.port)).unwrap();
    let mut daemon = home.start();
    assert_eq!(exit_code(&mut daemon), 4, "{}", daemon.log_text());
    assert!(
        daemon.log_text().contains("metrics.bind"),
        "{}",
        daemon.log_text()
    );
    drop(squatter);

    // The state folder held by a running daemon: exit 4 for the second one (its own port).
    let mut first = home.start();
    home.wait_healthy(&mut first);
    let text = std::fs::read_to_string(home.config()).unwrap();
    let second_config = home.path().join("second.toml");
    let port = choreod_tests::daemon::free_port();
    std::fs::write(
        &second_config,
        text.replace(&home.port.to_string(), &port.to_string()),
    )
    .unwrap();
    let second = choreod_tests::choreod()
        .args(["serve", "--config"])
        .arg(&second_config)
        .output()
        .unwrap();
    let stderr = String::from_utf8_lossy(&second.stderr);
    assert_eq!(second.status.code(), Some(4), "{stderr}");
    assert!(stderr.contains("is locked"), "{stderr}");
}

#[test]
fn refuses_to_start_on_a_bad_config_or_a_spool_in_use() {
    let mut home = Home::new("");
    std::fs::remove_dir(home.inbox()).unwrap();
    let mut daemon = home.start();
    let status = daemon.wait_exit(Duration::from_secs(30)).expect("exits");
    assert_eq!(status.code(), Some(3), "{}", daemon.log_text());
    let log = daemon.log_text();
    assert!(
        log.contains("choreod: error: ") && log.contains("`paths.inbox`"),
        "{log}"
    );
    assert!(log.contains("does not exist"), "{log}");

    std::fs::create_dir(home.inbox()).unwrap();
    let mut first = home.start();
    home.wait_healthy(&mut first);
    // Same state folder, another metrics port.
    let text = std::fs::read_to_string(home.path().join("choreod.toml")).unwrap();
    let other = choreod_tests::daemon::free_port();
    let text = text.replace(&format!(":{}\"", home.port), &format!(":{other}\""));
    std::fs::write(home.path().join("choreod.toml"), text).unwrap();
    let mut second = home.start();
    let status = second
        .wait_exit(Duration::from_secs(30))
        .expect("the second one exits");
    assert_eq!(status.code(), Some(4), "{}", second.log_text());
    assert!(
        second.log_text().contains("another choreod serve"),
        "{}",
        second.log_text()
    );
    assert!(first.try_status().is_none(), "the first one keeps running");
}
