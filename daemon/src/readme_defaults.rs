//! The defaults the README states are the code's. A flag's default is read from the command
//! line's definition (what `--help` prints, itself taken from the library's option types and
//! the config's constants), a config key's from the validated config of a minimal file; the
//! README's number is the one written right after a phrase that must occur in it exactly once.

use std::path::Path;

use clap::CommandFactory;

use crate::commands::Cli;

/// The README with every run of whitespace as one space: sentences wrap across lines.
fn readme() -> String {
    include_str!("../../README.md")
        .split_whitespace()
        .collect::<Vec<_>>()
        .join(" ")
}

/// What the README writes right after `phrase` (which it must say exactly once), up to the
/// first character that cannot be part of a number; thousands separators dropped.
fn stated(readme: &str, phrase: &str) -> f64 {
    let mut hits = readme.match_indices(phrase);
    let (at, _) = hits
        .next()
        .unwrap_or_else(|| panic!("the README no longer says {phrase:?}"));
    assert!(
        hits.next().is_none(),
        "the README says {phrase:?} more than once: make the phrase longer"
    );
    let number: String = readme[at + phrase.len()..]
        .chars()
        .take_while(|c| c.is_ascii_digit() || matches!(c, '-' | '.' | ','))
        .collect();
    let number = number.trim_end_matches(['.', ',']).replace(',', "");
    number
        .parse()
        .unwrap_or_else(|_| panic!("the README's {phrase:?} is followed by no number"))
}

/// The default of `--flag` of the verb `path` (`["models", "check"]`), as `--help` prints it.
fn flag_default(path: &[&str], flag: &str) -> f64 {
    let mut command = Cli::command();
    for name in path {
        command = command
            .find_subcommand(name)
            .unwrap_or_else(|| panic!("no verb {name}"))
            .clone();
    }
    let arg = command
        .get_arguments()
        .find(|a| a.get_long() == Some(flag))
        .unwrap_or_else(|| panic!("{path:?} has no --{flag}"));
    let value = arg
        .get_default_values()
        .first()
        .unwrap_or_else(|| panic!("{path:?} --{flag} has no default"));
    value
        .to_str()
        .and_then(|v| v.parse().ok())
        .unwrap_or_else(|| panic!("{path:?} --{flag}: default {value:?} is not a number"))
}

/// The config every key of which is at its default (only the required paths given).
fn default_config() -> choreo_config::Config {
    let minimal = "[paths]\ninbox = \"in\"\noutput = \"out\"\nstate = \"st\"\n";
    choreo_config::RawConfig::parse(minimal)
        .and_then(|raw| raw.validate(Path::new("/base")))
        .unwrap_or_else(|e| panic!("{e}"))
}

#[test]
fn the_flag_defaults_the_readme_states_are_the_flags_defaults() {
    let readme = readme();
    let cases: &[(&str, &[&str], &str)] = &[
        (
            "after `--time-limit SECONDS` (default ",
            &["dance"],
            "time-limit",
        ),
        (
            "after `--time-limit SECONDS` (default ",
            &["stylize"],
            "time-limit",
        ),
        (
            "`models check`'s test run after `--time-limit` (default ",
            &["models", "check"],
            "time-limit",
        ),
        (
            "take `--time-limit SECONDS` (default ",
            &["models", "check"],
            "time-limit",
        ),
        (
            "`--chunk-windows` (windows per batch, default ",
            &["dance"],
            "chunk-windows",
        ),
        (
            "(`--chunk-segments` at a time, default ",
            &["stylize"],
            "chunk-segments",
        ),
        (
            "more values than `--max-elements` (default ",
            &["convert"],
            "max-elements",
        ),
        ("`--start-bpm` (default ", &["beats"], "start-bpm"),
        ("**BAS** is scored at ", &["eval"], "bas-fps"),
        ("Every hop (`--hop`, default ", &["live"], "hop"),
        ("down to `--min-steps` (default ", &["live"], "min-steps"),
        ("(`latency_budget_s`, default ", &["live"], "latency-budget"),
        ("`live.nice` (default ", &["live"], "nice"),
    ];
    for (phrase, verb, flag) in cases {
        assert_eq!(
            stated(&readme, phrase),
            flag_default(verb, flag),
            "README {phrase:?} vs {verb:?} --{flag}"
        );
    }
}

#[test]
fn the_config_defaults_the_readme_states_are_the_configs() {
    let readme = readme();
    let c = default_config();
    let cases = [
        (
            "jobs after `job.time_limit_s` (default ",
            c.job.time_limit_s,
        ),
        ("`serve.settle_ms` (default ", c.serve.settle_ms as f64),
        (
            "`serve.max_attempts` (default ",
            f64::from(c.serve.max_attempts),
        ),
        (
            "`serve.shutdown_timeout_s` (default ",
            c.serve.shutdown_timeout_s,
        ),
        ("# hop_s = ", c.live.hop_s),
        ("min_steps = ", c.live.min_steps as f64),
        ("sampler, seed = ", c.live.seed as f64),
        ("intra_threads = ", c.live.intra_threads as f64),
        ("# latency_budget_s = ", c.live.latency_budget_s),
        ("# nice = ", f64::from(c.live.nice)),
    ];
    for (phrase, value) in cases {
        assert_eq!(stated(&readme, phrase), value, "README {phrase:?}");
    }
    let bind = format!("`metrics.bind` (default `{}`", c.metrics.bind);
    assert!(readme.contains(&bind), "the README should say {bind}");
}

/// The config cannot name the models crate's defaults (config does not depend on models), so the
/// limits it shares with the song pipeline are written twice; this ties them: a config left at
/// its defaults dances exactly as the library's default options do.
#[test]
fn a_config_at_its_defaults_gives_the_song_pipelines_default_options() {
    let c = default_config();
    assert_eq!(
        crate::settings::song_options(&c),
        choreo_models::SongOptions::default(),
        "[job]/[limits] defaults differ from SongOptions::default()"
    );
    let live = crate::settings::live_options(&c.live);
    assert_eq!(live.dance, choreo_models::DanceOptions::default());
}
