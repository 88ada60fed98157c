//! Progress of long commands (`generate`, `pretrain`, `probe`, `embed`) on stderr: a bar on a terminal,
//! otherwise a line every few seconds (done/total, rate, ETA) for logs; nothing with `--quiet`.

use std::io::IsTerminal;
use std::sync::Mutex;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::time::{Duration, Instant};

use indicatif::{ProgressBar, ProgressStyle};

static QUIET: AtomicBool = AtomicBool::new(false);
static INTERVAL_MS: AtomicU64 = AtomicU64::new(5000);

/// Sets the global `--quiet` and `--progress-interval` choices (before any [`Progress`]).
pub fn configure(quiet: bool, interval_s: f64) {
    QUIET.store(quiet, Ordering::Relaxed);
    INTERVAL_MS.store((interval_s * 1e3).round() as u64, Ordering::Relaxed);
}

/// Whether `--quiet` was given.
pub fn quiet() -> bool {
    QUIET.load(Ordering::Relaxed)
}

/// Progress of one command over `total` units of work.
#[derive(Debug)]
pub struct Progress {
    label: &'static str,
    unit: &'static str,
    total: u64,
    done: AtomicU64,
    bar: Option<ProgressBar>,
    lines: Option<Mutex<Lines>>,
}

#[derive(Debug)]
struct Lines {
    interval: Duration,
    rate: Rate,
    last: Instant,
    message: String,
}

/// Units per second since the first report: the time before it (loading data, building a
/// model, pretraining's step-0 probe) and the units done before it (a resumed run starts
/// part-way) are not counted, so the first figures are not skewed by a slow start.
#[derive(Debug, Default)]
struct Rate {
    /// When the first report came, and the units done then.
    first: Option<(Instant, u64)>,
}

impl Rate {
    /// The rate at `now` with `done` units done; 0 (unknown) at the first report.
    fn at(&mut self, now: Instant, done: u64) -> f64 {
        let (t0, done0) = *self.first.get_or_insert((now, done));
        let elapsed = now.duration_since(t0).as_secs_f64();
        if elapsed > 0.0 {
            done.saturating_sub(done0) as f64 / elapsed
        } else {
            0.0
        }
    }
}

impl Progress {
    /// Progress of `label` (the command) over `total` `unit`s (singular, e.g. `frame`).
    pub fn new(label: &'static str, unit: &'static str, total: u64) -> Progress {
        let quiet = QUIET.load(Ordering::Relaxed);
        let terminal = std::io::stderr().is_terminal();
        let bar = (!quiet && terminal).then(|| {
            ProgressBar::new(total).with_style(
                ProgressStyle::with_template(&format!(
                    "{{elapsed_precise}} {{bar:40}} {{pos}}/{{len}} {unit}s, {{per_sec}}, eta {{eta}} {{msg}}"
                ))
                .expect("valid template"),
            )
        });
        let now = Instant::now();
        let lines = (!quiet && !terminal).then(|| {
            Mutex::new(Lines {
                interval: Duration::from_millis(INTERVAL_MS.load(Ordering::Relaxed)),
                rate: Rate::default(),
                last: now,
                message: String::new(),
            })
        });
        Progress {
            label,
            unit,
            total,
            done: AtomicU64::new(0),
            bar,
            lines,
        }
    }

    /// `n` more units done.
    pub fn inc(&self, n: u64) {
        let done = self.done.fetch_add(n, Ordering::Relaxed) + n;
        if let Some(bar) = &self.bar {
            bar.inc(n);
        }
        self.tick(done);
    }

    /// `done` units done in all (a resumed run starts part-way; its rate counts from there).
    pub fn set(&self, done: u64) {
        self.done.store(done, Ordering::Relaxed);
        if let Some(bar) = &self.bar {
            bar.set_position(done);
        }
        self.tick(done);
    }

    /// Text shown after the counts (e.g. the last loss).
    pub fn set_message(&self, message: String) {
        if let Some(lines) = &self.lines {
            lines.lock().expect("no poisoned lock").message = message.clone();
        }
        if let Some(bar) = &self.bar {
            bar.set_message(message);
        }
    }

    /// Removes the bar (the command's own summary follows).
    pub fn finish(&self) {
        if let Some(bar) = &self.bar {
            bar.finish_and_clear();
        }
    }

    fn tick(&self, done: u64) {
        let Some(lines) = &self.lines else { return };
        let mut lines = lines.lock().expect("no poisoned lock");
        let now = Instant::now();
        let rate = lines.rate.at(now, done);
        if now.duration_since(lines.last) < lines.interval {
            return;
        }
        lines.last = now;
        let line = progress_line(
            self.label,
            self.unit,
            done,
            self.total,
            rate,
            &lines.message,
        );
        eprintln!("{line}");
    }
}

/// `generate: 120/960 frames (12 %), 35.2 frames/s, ETA 24 s; MESSAGE`.
fn progress_line(
    label: &str,
    unit: &str,
    done: u64,
    total: u64,
    rate: f64,
    message: &str,
) -> String {
    let pct = if total == 0 {
        100.0
    } else {
        100.0 * done as f64 / total as f64
    };
    let speed = if rate >= 1.0 {
        format!("{rate:.1} {unit}s/s")
    } else if rate > 0.0 {
        format!("{:.2} s/{unit}", 1.0 / rate)
    } else {
        format!("– {unit}s/s")
    };
    let eta = if done >= total {
        "done".to_string()
    } else if rate > 0.0 {
        format!("ETA {}", duration_text((total - done) as f64 / rate))
    } else {
        "ETA –".to_string()
    };
    let tail = if message.is_empty() {
        String::new()
    } else {
        format!("; {}", message.trim())
    };
    format!("{label}: {done}/{total} {unit}s ({pct:.0} %), {speed}, {eta}{tail}")
}

/// `45 s`, `3 min 05 s`, `2 h 07 min`.
fn duration_text(seconds: f64) -> String {
    let s = seconds.round().max(0.0) as u64;
    if s < 60 {
        format!("{s} s")
    } else if s < 3600 {
        format!("{} min {:02} s", s / 60, s % 60)
    } else {
        format!("{} h {:02} min", s / 3600, (s % 3600) / 60)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn line_says_done_total_rate_and_eta() {
        assert_eq!(
            progress_line("generate", "frame", 120, 960, 35.0, ""),
            "generate: 120/960 frames (12 %), 35.0 frames/s, ETA 24 s"
        );
        assert_eq!(
            progress_line("pretrain", "step", 10, 200, 0.5, "loss 0.1000"),
            "pretrain: 10/200 steps (5 %), 2.00 s/step, ETA 6 min 20 s; loss 0.1000"
        );
        assert_eq!(
            progress_line("probe", "fit", 6, 6, 2.0, ""),
            "probe: 6/6 fits (100 %), 2.0 fits/s, done"
        );
        assert_eq!(duration_text(7322.0), "2 h 02 min");
        assert_eq!(
            progress_line("pretrain", "step", 1, 200, 0.0, ""),
            "pretrain: 1/200 steps (0 %), – steps/s, ETA –"
        );
    }

    /// The rate counts from the first report: a slow start (a resumed run's earlier steps, or
    /// a minute of setup before the first step) does not enter it.
    #[test]
    fn rate_counts_from_the_first_report() {
        let mut rate = Rate::default();
        let t0 = Instant::now();
        assert_eq!(rate.at(t0 + Duration::from_secs(60), 100), 0.0);
        let r = rate.at(t0 + Duration::from_secs(64), 102);
        assert!((r - 0.5).abs() < 1e-12, "{r}");
    }
}
