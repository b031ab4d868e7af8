//! Estimated time to go (MAUVET's ETA): the distance left divided by the speed flown so far.
//!
//! The speed is a moving average of the ground speeds the vehicle reports while it moves, so
//! the estimate follows what the vehicle really does (wind, a slower autopilot cruise speed,
//! a speed-up of the simulator) rather than what the plan asks for. Samples of a stopped
//! vehicle (before the start, paused) are left out: they would make the estimate grow without
//! bound while nothing is flown.

/// Below this ground speed, m/s, the vehicle counts as stopped.
pub const MOVING_MPS: f64 = 0.2;

/// Weight of each new sample in the moving average.
const ALPHA: f64 = 0.1;

/// The speed-flown estimator.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct EtaEstimator {
    speed: Option<f64>,
}

impl EtaEstimator {
    /// An estimator that has seen nothing yet.
    pub fn new() -> Self {
        Self::default()
    }

    /// A ground speed sample, m/s. Stopped or invalid samples are ignored.
    pub fn observe(&mut self, ground_speed: f64) {
        if !(ground_speed.is_finite() && ground_speed >= MOVING_MPS) {
            return;
        }
        self.speed = Some(match self.speed {
            None => ground_speed,
            Some(s) => s + ALPHA * (ground_speed - s),
        });
    }

    /// The average speed flown, m/s, once the vehicle has moved.
    pub fn speed(&self) -> Option<f64> {
        self.speed
    }

    /// Seconds to fly `remaining_m` at the speed flown; `None` before the vehicle has moved.
    pub fn eta_s(&self, remaining_m: f64) -> Option<f64> {
        let s = self.speed?;
        remaining_m.is_finite().then(|| remaining_m.max(0.0) / s)
    }

    /// Forgets the speed (a new plan, perhaps another vehicle behaviour).
    pub fn reset(&mut self) {
        self.speed = None;
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn no_eta_before_the_vehicle_moves() {
        let mut e = EtaEstimator::new();
        assert_eq!(e.eta_s(100.0), None);
        e.observe(0.0);
        e.observe(f64::NAN);
        e.observe(0.1);
        assert_eq!(e.eta_s(100.0), None);
    }

    #[test]
    fn the_eta_follows_the_speed_flown() {
        let mut e = EtaEstimator::new();
        e.observe(2.0);
        assert_eq!(e.eta_s(100.0), Some(50.0));
        // Stops do not count; a slower vehicle converges to its speed.
        e.observe(0.0);
        assert_eq!(e.speed(), Some(2.0));
        for _ in 0..100 {
            e.observe(1.0);
        }
        let eta = e.eta_s(100.0).unwrap();
        assert!((eta - 100.0).abs() < 0.1, "{eta}");
        // Nothing left, nothing to wait; never negative.
        assert_eq!(e.eta_s(0.0), Some(0.0));
        assert_eq!(e.eta_s(-5.0), Some(0.0));
        assert_eq!(e.eta_s(f64::INFINITY), None);
        e.reset();
        assert_eq!(e.speed(), None);
    }
}
