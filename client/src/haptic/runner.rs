//! The haptic thread and its handle.

use std::sync::Arc;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::mpsc;
use std::thread::JoinHandle;
use std::time::{Duration, Instant};

use nalgebra::Vector3;

use super::render::{ForceRenderer, HapticModel, RenderConfig};
use super::teaching::{TeachingPlayback, TeachingRecorder};
use super::timing::{HapticStats, Pacer, PeriodHistogram};
use super::{HapticDevice, HapticError, Latest, ToolInput};

/// Configuration of a haptic loop.
#[derive(Debug, Clone, Copy)]
pub struct HapticConfig {
    /// Tick period (1 ms = 1 kHz).
    pub period: Duration,
    /// Busy-wait for the last part of each period instead of sleeping (0: sleep only).
    pub spin: Duration,
    /// Force limits, rate limit and fades.
    pub render: RenderConfig,
    /// Fade the force out when the newest model is older than this (`None`: never).
    /// Measured from the loop time at which the loop first saw that model.
    pub model_timeout: Option<Duration>,
    /// Cut-off of the low-pass filter on the device velocity (for the guide damping), Hz.
    pub velocity_cutoff_hz: f64,
    /// Called once on the haptic thread before the first tick, e.g. to give it real-time
    /// priority (`libc::sched_setscheduler(0, SCHED_FIFO, …)` or `chrt -f -p 80 TID`;
    /// the thread id is in `/proc/thread-self`). Without it the thread runs at normal
    /// priority and shares the cores with everything else.
    pub thread_setup: Option<fn()>,
}

impl Default for HapticConfig {
    fn default() -> Self {
        HapticConfig {
            period: Duration::from_millis(1),
            spin: Duration::from_micros(50),
            render: RenderConfig::default(),
            model_timeout: Some(Duration::from_millis(500)),
            velocity_cutoff_hz: 50.0,
            thread_setup: None,
        }
    }
}

impl HapticConfig {
    fn validate(&self) -> Result<(), HapticError> {
        let inv = |key, problem: &str| {
            Err(HapticError::Invalid {
                key,
                problem: problem.into(),
            })
        };
        if self.period < Duration::from_micros(100) || self.period > Duration::from_millis(100) {
            return inv("period", "must be within 0.1–100 ms");
        }
        if self.spin > self.period {
            return inv("spin", "must not exceed the period");
        }
        let r = &self.render;
        if !(r.max_force.is_finite() && r.max_force >= 0.0) {
            return inv("max_force", "must be finite and ≥ 0 N");
        }
        if !(r.max_torque.is_finite() && r.max_torque >= 0.0) {
            return inv("max_torque", "must be finite and ≥ 0 N·m");
        }
        if r.max_force_rate.is_nan() || r.max_force_rate <= 0.0 {
            return inv("max_force_rate", "must be > 0 N/s (infinity: off)");
        }
        if !(r.fade_out >= 0.0 && r.fade_in >= 0.0) {
            return inv("fade_out/fade_in", "must be ≥ 0 s");
        }
        if self.velocity_cutoff_hz.is_nan() || self.velocity_cutoff_hz <= 0.0 {
            return inv("velocity_cutoff_hz", "must be > 0 Hz");
        }
        Ok(())
    }
}

struct Shared {
    model: Latest<HapticModel>,
    input: Latest<ToolInput>,
    stop: AtomicBool,
    ticks: AtomicU64,
    /// The device's input was stale at the newest tick.
    input_stale: AtomicBool,
}

/// The playback time of a teaching guide, s, read once per tick on the haptic thread (it
/// must not block). Without one, playback time is loop time since the guide started.
pub type GuideClock = Arc<dyn Fn() -> f64 + Send + Sync>;

enum Command {
    Guide(Option<(Box<TeachingPlayback>, Option<GuideClock>)>),
    StartRecording(TeachingRecorder),
    StopRecording(mpsc::Sender<Option<TeachingRecorder>>),
}

/// The simulation thread's side: publishes models (newest wins, never blocks the loop).
#[derive(Clone)]
pub struct ModelWriter(Arc<Shared>);

impl ModelWriter {
    /// Publishes the model of the newest simulation step.
    pub fn publish(&self, model: &HapticModel) {
        self.0.model.store(model);
    }
}

/// The simulation thread's side: reads the newest device input.
#[derive(Clone)]
pub struct InputReader(Arc<Shared>);

impl InputReader {
    /// The newest input and its version (1, 2, … per tick), or `None` before the first
    /// tick.
    pub fn latest(&self) -> Option<(u64, ToolInput)> {
        self.0.input.load()
    }

    /// Whether the device reported stale input at the newest tick (e.g. no datagram from
    /// a UDP driver yet, or for longer than its stale timeout).
    pub fn stale(&self) -> bool {
        self.0.input_stale.load(Ordering::Relaxed)
    }
}

/// A running haptic loop. Dropping it stops the loop (the device is dropped too); use
/// [`stop`](Self::stop) to get the device and the statistics back.
pub struct HapticHandle<D: HapticDevice + 'static> {
    shared: Arc<Shared>,
    commands: mpsc::Sender<Command>,
    thread: Option<JoinHandle<(D, HapticStats)>>,
    name: String,
}

/// Starts a haptic loop on a new OS thread named `haptic`.
pub fn spawn<D: HapticDevice + 'static>(
    device: D,
    config: HapticConfig,
) -> Result<HapticHandle<D>, HapticError> {
    spawn_with_model(device, config, None)
}

/// Starts a haptic loop with an initial model already published (so that the first tick
/// renders it).
pub fn spawn_with_model<D: HapticDevice + 'static>(
    device: D,
    config: HapticConfig,
    model: Option<&HapticModel>,
) -> Result<HapticHandle<D>, HapticError> {
    config.validate()?;
    let shared = Arc::new(Shared {
        model: Latest::new(),
        input: Latest::new(),
        stop: AtomicBool::new(false),
        ticks: AtomicU64::new(0),
        input_stale: AtomicBool::new(true),
    });
    if let Some(m) = model {
        shared.model.store(m);
    }
    let (tx, rx) = mpsc::channel();
    let name = device.name().to_string();
    let s = shared.clone();
    let thread = std::thread::Builder::new()
        .name("haptic".into())
        .spawn(move || run(device, config, &s, rx))
        .map_err(|e| HapticError::io("spawning the haptic thread", e))?;
    Ok(HapticHandle {
        shared,
        commands: tx,
        thread: Some(thread),
        name,
    })
}

impl<D: HapticDevice + 'static> HapticHandle<D> {
    /// A writer for the simulation thread.
    pub fn model_writer(&self) -> ModelWriter {
        ModelWriter(self.shared.clone())
    }

    /// A reader for the simulation thread.
    pub fn input_reader(&self) -> InputReader {
        InputReader(self.shared.clone())
    }

    /// Publishes a model (same as `model_writer().publish`).
    pub fn publish_model(&self, model: &HapticModel) {
        self.shared.model.store(model);
    }

    /// The newest device input.
    pub fn latest_input(&self) -> Option<ToolInput> {
        self.shared.input.load().map(|(_, i)| i)
    }

    /// Ticks run so far.
    pub fn ticks(&self) -> u64 {
        self.shared.ticks.load(Ordering::Relaxed)
    }

    /// The device's name.
    pub fn device_name(&self) -> &str {
        &self.name
    }

    /// Whether the thread is still running.
    pub fn is_running(&self) -> bool {
        self.thread.as_ref().is_some_and(|t| !t.is_finished())
    }

    /// Starts (or replaces, `None`: ends) teaching playback; its time starts at the tick
    /// that receives it.
    pub fn set_guide(&self, guide: Option<TeachingPlayback>) {
        let _ = self
            .commands
            .send(Command::Guide(guide.map(|g| (Box::new(g), None))));
    }

    /// Starts (or replaces) teaching playback with its time taken from `clock` (s) each
    /// tick instead of loop time, e.g. the simulation's time since the trainee's act began,
    /// so that the guide stays in step with a simulation that runs slower than real time.
    pub fn set_guide_with_clock(&self, guide: TeachingPlayback, clock: GuideClock) {
        let _ = self
            .commands
            .send(Command::Guide(Some((Box::new(guide), Some(clock)))));
    }

    /// Starts recording the device's trajectory into `recorder` (replaces a running one).
    pub fn start_recording(&self, recorder: TeachingRecorder) {
        let _ = self.commands.send(Command::StartRecording(recorder));
    }

    /// Ends recording and returns the recorder (`None` if none was running or the loop
    /// ended). Waits at most a second for the haptic thread.
    pub fn stop_recording(&self) -> Option<TeachingRecorder> {
        let (tx, rx) = mpsc::channel();
        self.commands.send(Command::StopRecording(tx)).ok()?;
        rx.recv_timeout(Duration::from_secs(1)).ok().flatten()
    }

    /// Stops the loop and returns the device and the statistics.
    pub fn stop(mut self) -> (D, HapticStats) {
        self.shared.stop.store(true, Ordering::Relaxed);
        let t = self.thread.take().expect("thread present until stop");
        match t.join() {
            Ok(r) => r,
            Err(p) => std::panic::resume_unwind(p),
        }
    }
}

impl<D: HapticDevice + 'static> Drop for HapticHandle<D> {
    fn drop(&mut self) {
        self.shared.stop.store(true, Ordering::Relaxed);
        if let Some(t) = self.thread.take() {
            let _ = t.join();
        }
    }
}

fn run<D: HapticDevice>(
    mut device: D,
    cfg: HapticConfig,
    shared: &Shared,
    commands: mpsc::Receiver<Command>,
) -> (D, HapticStats) {
    if let Some(setup) = cfg.thread_setup {
        setup();
    }
    if let Ok(p) = std::fs::read_link("/proc/thread-self") {
        tracing::debug!(device = device.name(), thread = %p.display(), "haptic loop started");
    }
    let period_s = cfg.period.as_secs_f64();
    let mut renderer = ForceRenderer::new(cfg.render, period_s);
    let mut hist = PeriodHistogram::new();
    let mut lateness = PeriodHistogram::new();
    let mut stats = HapticStats {
        ticks: 0,
        rate_hz: f64::NAN,
        period_p50_us: f64::NAN,
        period_p99_us: f64::NAN,
        period_max_us: f64::NAN,
        jitter_p99_us: f64::NAN,
        lateness_p99_us: f64::NAN,
        overruns: 0,
        reanchors: 0,
        max_force: 0.0,
        clamped_ticks: 0,
        stale_input_ticks: 0,
        stale_model_ticks: 0,
        model_read_misses: 0,
        models_seen: 0,
        guide_ticks: 0,
        guide_force_max: 0.0,
        guide_force_mean: 0.0,
    };
    let mut guide_force_sum = 0.0;
    let mut model: Option<HapticModel> = None;
    let mut model_version = 0u64;
    let mut model_seen_at = Duration::ZERO;
    let mut guide: Option<(Box<TeachingPlayback>, Option<GuideClock>, Duration)> = None;
    let mut recorder: Option<TeachingRecorder> = None;
    let mut prev_x: Option<(Duration, Vector3<f64>)> = None;
    let mut velocity = Vector3::zeros();

    let start = Instant::now();
    let mut pacer = Pacer::new(start, cfg.period, cfg.spin);
    let mut first_tick: Option<Instant> = None;
    let mut last_tick = start;
    while !shared.stop.load(Ordering::Relaxed) {
        let (now, late) = pacer.wait();
        lateness.record(late);
        if first_tick.is_some() {
            hist.record(now - last_tick);
        } else {
            first_tick = Some(now);
        }
        last_tick = now;
        let t = now - start;

        // Commands (non-blocking).
        while let Ok(c) = commands.try_recv() {
            match c {
                Command::Guide(g) => guide = g.map(|(g, clock)| (g, clock, t)),
                Command::StartRecording(r) => recorder = Some(r),
                Command::StopRecording(reply) => {
                    let _ = reply.send(recorder.take());
                }
            }
        }

        // Device in.
        let input = device.read(t);
        let stale_input = device.input_stale();
        shared.input.store(&input);
        shared.input_stale.store(stale_input, Ordering::Relaxed);
        if let Some(r) = recorder.as_mut() {
            r.push(&input);
        }
        let x = input.position;
        if let Some((t0, x0)) = prev_x {
            let dt = (t - t0).as_secs_f64();
            if dt > 0.0 {
                let raw = (x - x0) / dt;
                let alpha = 1.0 - (-dt * 2.0 * std::f64::consts::PI * cfg.velocity_cutoff_hz).exp();
                velocity += (raw - velocity) * alpha;
            }
        }
        prev_x = Some((t, x));

        // Newest model.
        if shared.model.version() != model_version {
            match shared.model.try_load(4) {
                Some((v, m)) => {
                    model_version = v;
                    model = Some(m);
                    model_seen_at = t;
                    stats.models_seen += 1;
                }
                None => stats.model_read_misses += 1,
            }
        }
        let stale_model = model.is_some()
            && cfg
                .model_timeout
                .is_some_and(|limit| t.saturating_sub(model_seen_at) > limit);

        // Guide spring.
        let extra = match &guide {
            Some((g, clock, t0)) => {
                let tp = clock
                    .as_ref()
                    .map_or_else(|| (t - *t0).as_secs_f64(), |c| c());
                let f = g.guide_force(tp.max(0.0), &x, &velocity);
                let n = f.norm();
                if n.is_finite() {
                    stats.guide_ticks += 1;
                    stats.guide_force_max = stats.guide_force_max.max(n);
                    guide_force_sum += n;
                }
                f
            }
            None => Vector3::zeros(),
        };

        if stats.ticks == 0 && stale_input {
            renderer.set_gain(0.0); // nothing heard from a remote device yet
        }
        let out = renderer.tick(model.as_ref(), &x, extra, stale_input || stale_model);
        device.apply(out.force, out.torque);

        stats.ticks += 1;
        shared.ticks.store(stats.ticks, Ordering::Relaxed);
        stats.max_force = stats.max_force.max(out.force.norm());
        stats.clamped_ticks += u64::from(out.clamped);
        stats.stale_input_ticks += u64::from(stale_input);
        stats.stale_model_ticks += u64::from(stale_model);
    }
    // Leave the device without force.
    device.apply(Vector3::zeros(), Vector3::zeros());

    if stats.guide_ticks > 0 {
        stats.guide_force_mean = guide_force_sum / stats.guide_ticks as f64;
    }
    stats.overruns = pacer.overruns;
    stats.reanchors = pacer.reanchors;
    if let Some(first) = first_tick
        && stats.ticks > 1
    {
        let span = (last_tick - first).as_secs_f64();
        if span > 0.0 {
            stats.rate_hz = (stats.ticks - 1) as f64 / span;
        }
    }
    stats.period_p50_us = hist.percentile_us(50.0);
    stats.period_p99_us = hist.percentile_us(99.0);
    stats.period_max_us = hist.max_us();
    stats.jitter_p99_us = hist.jitter_percentile_us(cfg.period, 99.0);
    stats.lateness_p99_us = lateness.percentile_us(99.0);
    tracing::debug!(
        device = device.name(),
        "haptic loop stopped: {}",
        stats.summary()
    );
    (device, stats)
}
