//! Seeded, opt-in fault injection for device simulators.
//!
//! A simulator asks a [`FaultInjector`] before sending each reply whether to corrupt
//! it, and how. Faults are drawn from a [`FaultConfig`]: which kinds, with what
//! probability, on which class of reply (queries, which a driver may safely re-send,
//! or commands that move hardware, which it must never re-send blindly), after how
//! many clean replies, and at most how many times. The random stream is a
//! SplitMix64 generator seeded from the config, so a run is reproducible.
//!
//! What each fault does on the wire is protocol-specific and documented in the
//! simulator and in `protocols/<device>.md`; the driver's defined outcome for each
//! is tested in `tests/stage.rs`.

use std::time::Duration;

/// A kind of fault a simulator can inject.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum FaultKind {
    /// The reply is sent late, after [`FaultConfig::late_by`].
    LateReply,
    /// One byte of the reply's content is dropped.
    DroppedByte,
    /// One byte of the reply is replaced by a non-ASCII byte (Zaber: the checksum
    /// no longer matches).
    Garbled,
    /// An unsolicited message (GRBL `[MSG:..]`, Zaber `!` alert / `#` info) is sent
    /// before the reply.
    Unsolicited,
    /// The device resets instead of replying (GRBL banner, Zaber position lost).
    DeviceReset,
    /// A limit switch trips (GRBL `ALARM:1`, Zaber `WL` flag) right after the reply.
    LimitTrip,
    /// The device disappears instead of replying (the pseudo-terminal hangs up).
    Disconnect,
}

impl FaultKind {
    /// Every fault kind, for sweeps.
    pub const ALL: [FaultKind; 7] = [
        FaultKind::LateReply,
        FaultKind::DroppedByte,
        FaultKind::Garbled,
        FaultKind::Unsolicited,
        FaultKind::DeviceReset,
        FaultKind::LimitTrip,
        FaultKind::Disconnect,
    ];
}

/// Which replies a fault may hit.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum FaultTarget {
    /// Any reply.
    Any,
    /// Replies to queries (status, position, settings): safe for a driver to retry.
    Queries,
    /// Replies to commands that change the device (moves, homing, unlock).
    Commands,
}

/// The class of one reply, as the simulator sees it.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum ReplyClass {
    /// A reply to a query.
    Query,
    /// A reply to a command that changes the device.
    Command,
}

/// Opt-in fault configuration for one simulator.
#[derive(Debug, Clone, PartialEq)]
pub struct FaultConfig {
    /// Seed of the random stream (which reply, which kind, which byte).
    pub seed: u64,
    /// Kinds to draw from (uniformly).
    pub kinds: Vec<FaultKind>,
    /// Probability that an eligible reply is faulted, 0..=1.
    pub probability: f64,
    /// Which replies are eligible.
    pub target: FaultTarget,
    /// Number of eligible replies passed untouched before faults may start.
    pub skip: u32,
    /// At most this many faults in total.
    pub max_faults: u32,
    /// Delay of a [`FaultKind::LateReply`].
    pub late_by: Duration,
}

impl FaultConfig {
    /// Exactly one fault of `kind` on the first eligible reply of `target` after
    /// `skip` clean ones: the deterministic form the tests use.
    pub fn once(kind: FaultKind, target: FaultTarget, skip: u32) -> Self {
        FaultConfig {
            seed: 1,
            kinds: vec![kind],
            probability: 1.0,
            target,
            skip,
            max_faults: 1,
            late_by: Duration::from_millis(1500),
        }
    }
}

/// Draws faults from a [`FaultConfig`].
#[derive(Debug, Clone)]
pub struct FaultInjector {
    config: FaultConfig,
    state: u64,
    eligible_seen: u32,
    injected: u32,
}

impl FaultInjector {
    /// A new injector; its random stream starts from the config's seed.
    pub fn new(config: FaultConfig) -> Self {
        let state = config.seed;
        FaultInjector {
            config,
            state,
            eligible_seen: 0,
            injected: 0,
        }
    }

    /// The configuration.
    pub fn config(&self) -> &FaultConfig {
        &self.config
    }

    /// Number of faults injected so far.
    pub fn injected(&self) -> u32 {
        self.injected
    }

    /// Decides whether the next reply of `class` is faulted, and how.
    pub fn decide(&mut self, class: ReplyClass) -> Option<FaultKind> {
        let eligible = match self.config.target {
            FaultTarget::Any => true,
            FaultTarget::Queries => class == ReplyClass::Query,
            FaultTarget::Commands => class == ReplyClass::Command,
        };
        if !eligible || self.config.kinds.is_empty() || self.injected >= self.config.max_faults {
            return None;
        }
        self.eligible_seen += 1;
        if self.eligible_seen <= self.config.skip {
            return None;
        }
        if self.unit() >= self.config.probability {
            return None;
        }
        self.injected += 1;
        let i = self.index(self.config.kinds.len());
        Some(self.config.kinds[i])
    }

    /// A uniform index below `n` (0 when `n` is 0), for choosing a byte to corrupt.
    pub fn index(&mut self, n: usize) -> usize {
        if n == 0 {
            return 0;
        }
        (self.next_u64() % n as u64) as usize
    }

    /// A uniform number in [0, 1).
    fn unit(&mut self) -> f64 {
        (self.next_u64() >> 11) as f64 / (1u64 << 53) as f64
    }

    /// SplitMix64 (Steele, Lea, Flood 2014): tiny, seedable, good enough to pick faults.
    fn next_u64(&mut self) -> u64 {
        self.state = self.state.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = self.state;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        z ^ (z >> 31)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn once_faults_exactly_the_first_eligible_reply_after_skip() {
        let mut inj = FaultInjector::new(FaultConfig::once(
            FaultKind::Garbled,
            FaultTarget::Commands,
            2,
        ));
        assert_eq!(inj.decide(ReplyClass::Query), None, "queries not eligible");
        assert_eq!(inj.decide(ReplyClass::Command), None, "skip 1");
        assert_eq!(inj.decide(ReplyClass::Command), None, "skip 2");
        assert_eq!(inj.decide(ReplyClass::Command), Some(FaultKind::Garbled));
        assert_eq!(inj.decide(ReplyClass::Command), None, "max_faults = 1");
        assert_eq!(inj.injected(), 1);
    }

    #[test]
    fn same_seed_gives_the_same_fault_sequence_and_rate_is_respected() {
        let cfg = FaultConfig {
            seed: 42,
            kinds: FaultKind::ALL.to_vec(),
            probability: 0.25,
            target: FaultTarget::Any,
            skip: 0,
            max_faults: u32::MAX,
            late_by: Duration::from_millis(10),
        };
        let run = |cfg: &FaultConfig| {
            let mut inj = FaultInjector::new(cfg.clone());
            (0..4000)
                .map(|_| inj.decide(ReplyClass::Query))
                .collect::<Vec<_>>()
        };
        let a = run(&cfg);
        assert_eq!(a, run(&cfg));
        let rate = a.iter().filter(|f| f.is_some()).count() as f64 / a.len() as f64;
        // Binomial sd = sqrt(0.25 * 0.75 / 4000) ~ 0.007; allow 4 sd.
        assert!((rate - 0.25).abs() < 0.03, "rate {rate}");
        for k in FaultKind::ALL {
            assert!(a.contains(&Some(k)), "{k:?} drawn at least once");
        }
    }
}
