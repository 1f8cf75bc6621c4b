//! Command-line arguments (clap `Args` derive) shared by the relay CLI and anything else that
//! wants to describe an impaired link with flags.
//!
//! The impairment flags start from `--preset` (default `none`) and override single fields.
//! `--direction` says which way(s) the result applies to; the other direction is a perfect
//! link. Delays are **one-way per direction**, so `--preset poor --direction both` gives a
//! ≈ 400 ms RTT. For an asymmetric link, chain two relays (one `--direction up`, one
//! `--direction down`) or use the library API with two configs.

use std::net::SocketAddr;

use clap::{Args, ValueEnum};

use crate::model::{ConfigError, GilbertElliott, ImpairmentConfig, JitterDist, Outage};

/// Which direction(s) of the link the impairment applies to. *Up* is client → upstream
/// (for an impaired endpoint: outgoing), *down* is upstream → client (incoming).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, ValueEnum)]
pub enum Direction {
    #[default]
    Both,
    Up,
    Down,
}

/// Flags describing one impairment (applied per `--direction`).
#[derive(Debug, Clone, Default, Args)]
pub struct ImpairArgs {
    /// Starting point: none, lan, metro, good, average, poor, intercontinental
    /// (one-way delay per direction; see the crate docs for the table).
    #[arg(long, value_name = "NAME")]
    pub preset: Option<String>,
    /// One-way base delay, milliseconds.
    #[arg(long, value_name = "MS")]
    pub delay: Option<f64>,
    /// Jitter, milliseconds (standard deviation for normal, half-width for uniform).
    #[arg(long, value_name = "MS")]
    pub jitter: Option<f64>,
    /// Jitter distribution.
    #[arg(long, value_enum, value_name = "DIST")]
    pub jitter_dist: Option<JitterDistArg>,
    /// Allow packets to be reordered by jitter (default: release order = send order).
    #[arg(long)]
    pub reorder: bool,
    /// Independent random loss, percent.
    #[arg(long, value_name = "PCT")]
    pub loss: Option<f64>,
    /// Gilbert–Elliott burst loss: P_GB,P_BG then optionally ,LOSS_BAD and ,LOSS_GOOD
    /// (probabilities 0–1; defaults 1 and 0, mean burst = 1/P_BG packets).
    #[arg(long, value_name = "P_GB,P_BG[,LOSS_BAD]")]
    pub burst: Option<String>,
    /// Duplication probability, percent.
    #[arg(long, value_name = "PCT")]
    pub dup: Option<f64>,
    /// Rate cap, kbit/s (token bucket).
    #[arg(long, value_name = "KBPS")]
    pub rate: Option<f64>,
    /// Token-bucket size, bytes.
    #[arg(long, value_name = "BYTES")]
    pub bucket: Option<u32>,
    /// Rate-cap queue limit, packets (overflow is dropped and counted as rate drops).
    #[arg(long, value_name = "PKTS")]
    pub queue: Option<usize>,
    /// Scheduled outage: START_S,DURATION_S (seconds from start; 100 % loss).
    #[arg(long, value_name = "START_S,DUR_S")]
    pub outage: Option<String>,
    /// Direction(s) the impairment applies to.
    #[arg(long, value_enum, default_value_t = Direction::Both)]
    pub direction: Direction,
    /// RNG seed (each direction and each relay client derive their own stream from it).
    #[arg(long, value_name = "N", default_value_t = 1)]
    pub seed: u64,
}

/// `--jitter-dist` values.
#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum)]
pub enum JitterDistArg {
    Normal,
    Uniform,
}

fn parse_floats(field: &'static str, text: &str) -> Result<Vec<f64>, ConfigError> {
    text.split(',')
        .map(|s| {
            s.trim().parse::<f64>().map_err(|e| ConfigError::Parse {
                field,
                text: text.to_string(),
                why: e.to_string(),
            })
        })
        .collect()
}

impl ImpairArgs {
    /// The configured impairment (before `--direction` is applied).
    pub fn impairment(&self) -> Result<ImpairmentConfig, ConfigError> {
        let mut c = ImpairmentConfig::preset(self.preset.as_deref().unwrap_or("none"))?;
        if let Some(v) = self.delay {
            c.delay_ms = v;
        }
        if let Some(v) = self.jitter {
            c.jitter_ms = v;
        }
        if let Some(v) = self.jitter_dist {
            c.jitter_dist = match v {
                JitterDistArg::Normal => JitterDist::Normal,
                JitterDistArg::Uniform => JitterDist::Uniform,
            };
        }
        if self.reorder {
            c.reorder = true;
        }
        if let Some(v) = self.loss {
            c.loss_pct = v;
        }
        if let Some(text) = &self.burst {
            let v = parse_floats("burst", text)?;
            if !(2..=4).contains(&v.len()) {
                return Err(ConfigError::Parse {
                    field: "burst",
                    text: text.clone(),
                    why: "expected P_GB,P_BG[,LOSS_BAD[,LOSS_GOOD]]".into(),
                });
            }
            let mut ge = GilbertElliott::new(v[0], v[1]);
            if let Some(&l) = v.get(2) {
                ge.loss_bad = l;
            }
            if let Some(&l) = v.get(3) {
                ge.loss_good = l;
            }
            c.burst = Some(ge);
        }
        if let Some(v) = self.dup {
            c.dup_pct = v;
        }
        if let Some(v) = self.rate {
            c.rate_kbps = Some(v);
        }
        if let Some(v) = self.bucket {
            c.bucket_bytes = v;
        }
        if let Some(v) = self.queue {
            c.queue_pkts = v;
        }
        if let Some(text) = &self.outage {
            let v = parse_floats("outage", text)?;
            if v.len() != 2 {
                return Err(ConfigError::Parse {
                    field: "outage",
                    text: text.clone(),
                    why: "expected START_S,DURATION_S".into(),
                });
            }
            c.outage = Some(Outage {
                start_s: v[0],
                duration_s: v[1],
            });
        }
        c.validate()?;
        Ok(c)
    }

    /// `(up, down)` configurations after applying `--direction`.
    pub fn configs(&self) -> Result<(ImpairmentConfig, ImpairmentConfig), ConfigError> {
        let c = self.impairment()?;
        let none = ImpairmentConfig::none();
        Ok(match self.direction {
            Direction::Both => (c.clone(), c),
            Direction::Up => (c, none),
            Direction::Down => (none, c),
        })
    }
}

/// `cosurg netem` arguments: a UDP relay between clients and one upstream server.
#[derive(Debug, Clone, Args)]
pub struct NetemArgs {
    /// Address clients send to.
    #[arg(long, value_name = "ADDR")]
    pub listen: SocketAddr,
    /// The real server.
    #[arg(long, value_name = "ADDR")]
    pub upstream: SocketAddr,
    /// Stop after this many seconds (default: run until Ctrl-C).
    #[arg(long, value_name = "S")]
    pub seconds: Option<f64>,
    /// Forget a client after this many idle seconds.
    #[arg(long, value_name = "S", default_value_t = 120.0)]
    pub client_timeout: f64,
    #[command(flatten)]
    pub impair: ImpairArgs,
}

#[cfg(test)]
mod tests {
    use super::*;
    use clap::Parser;

    #[derive(Parser)]
    struct Cli {
        #[command(flatten)]
        netem: NetemArgs,
    }

    fn parse(args: &[&str]) -> NetemArgs {
        let mut v = vec![
            "x",
            "--listen",
            "127.0.0.1:5000",
            "--upstream",
            "127.0.0.1:4433",
        ];
        v.extend_from_slice(args);
        Cli::try_parse_from(v).unwrap().netem
    }

    #[test]
    fn preset_with_overrides() {
        let a = parse(&[
            "--preset",
            "poor",
            "--loss",
            "3",
            "--burst",
            "0.01,0.3",
            "--rate",
            "500",
            "--queue",
            "20",
            "--reorder",
            "--jitter-dist",
            "uniform",
            "--seed",
            "9",
        ]);
        let (up, down) = a.impair.configs().unwrap();
        assert_eq!(up, down);
        assert_eq!(up.delay_ms, 200.0);
        assert_eq!(up.jitter_ms, 30.0);
        assert_eq!(up.loss_pct, 3.0);
        assert_eq!(up.burst, Some(GilbertElliott::new(0.01, 0.3)));
        assert_eq!(up.rate_kbps, Some(500.0));
        assert_eq!(up.queue_pkts, 20);
        assert!(up.reorder);
        assert_eq!(up.jitter_dist, JitterDist::Uniform);
        assert_eq!(a.impair.seed, 9);
    }

    #[test]
    fn direction_and_outage() {
        let a = parse(&["--delay", "10", "--outage", "5,2", "--direction", "down"]);
        let (up, down) = a.impair.configs().unwrap();
        assert!(up.is_passthrough());
        assert_eq!(down.delay_ms, 10.0);
        assert_eq!(
            down.outage,
            Some(Outage {
                start_s: 5.0,
                duration_s: 2.0
            })
        );
    }

    #[test]
    fn errors_are_reported() {
        assert!(parse(&["--preset", "mars"]).impair.configs().is_err());
        assert!(parse(&["--burst", "0.1"]).impair.configs().is_err());
        assert!(parse(&["--loss", "101"]).impair.configs().is_err());
        assert!(parse(&["--outage", "1,x"]).impair.configs().is_err());
    }
}
