//! The device side: the [`HapticDevice`] trait a real device's SDK plugs
//! into, and [`SimulatedDevice`], a scripted hand on a mass–spring arm for
//! tests and examples.

use nalgebra::{Isometry3, Translation3};

use crate::contact::Pose;
use crate::error::{Result, check_positive, check_range};
use crate::math::Vec3;

/// What a device can render.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct DeviceLimits {
    /// Largest force (newtons); the output is scaled down to it.
    pub max_force: f64,
    /// Largest torque (newton-metres).
    pub max_torque: f64,
}

impl Default for DeviceLimits {
    fn default() -> Self {
        Self {
            max_force: f64::INFINITY,
            max_torque: f64::INFINITY,
        }
    }
}

/// A haptic device, driven from the haptic thread.
///
/// A real device wraps its SDK here: [`Self::pose`] reads the stylus pose
/// (mapped into the scene's frame, metres), [`Self::set_output`] sends the
/// force and torque (newtons, newton-metres, scene frame) to the motors.
/// The haptic loop calls both once per tick, in that order, from its own
/// thread; [`Self::set_output`] with zeros is the last call before the loop
/// stops.
pub trait HapticDevice: Send + 'static {
    /// The device's pose at `time` (seconds since the loop started).
    fn pose(&mut self, time: f64) -> Pose;
    /// The force and the torque (about the pose's origin) to render.
    fn set_output(&mut self, force: Vec3, torque: Vec3);
    /// The device's limits (default: none).
    fn limits(&self) -> DeviceLimits {
        DeviceLimits::default()
    }
}

/// The hand of a [`SimulatedDevice`]: a point mass pulled toward the script
/// by a spring–damper (the arm), pushed back by the rendered force.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SimulatedHand {
    /// Mass (kg).
    pub mass: f64,
    /// Arm stiffness (N/m).
    pub stiffness: f64,
    /// Arm damping (N·s/m).
    pub damping: f64,
}

impl Default for SimulatedHand {
    /// A light, compliant hand: 0.1 kg on 200 N/m, damped at 60 % of critical.
    fn default() -> Self {
        Self {
            mass: 0.1,
            stiffness: 200.0,
            damping: 0.6 * 2.0 * (200.0f64 * 0.1).sqrt(),
        }
    }
}

impl SimulatedHand {
    fn validate(&self) -> Result<()> {
        check_positive("SimulatedHand::mass", self.mass)?;
        check_positive("SimulatedHand::stiffness", self.stiffness)?;
        check_range("SimulatedHand::damping", self.damping, 0.0, f64::MAX)?;
        Ok(())
    }
}

/// A script: the pose the hand aims for at a time (seconds).
pub type Script = Box<dyn FnMut(f64) -> Pose + Send>;

/// A device for tests and examples: a scripted motion, optionally through
/// a [`SimulatedHand`] that reacts to the force it receives.
pub struct SimulatedDevice {
    script: Script,
    hand: Option<SimulatedHand>,
    limits: DeviceLimits,
    time: f64,
    x: Vec3,
    v: Vec3,
    force: Vec3,
    torque: Vec3,
    started: bool,
}

impl std::fmt::Debug for SimulatedDevice {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("SimulatedDevice")
            .field("hand", &self.hand)
            .field("time", &self.time)
            .field("x", &self.x)
            .field("force", &self.force)
            .finish_non_exhaustive()
    }
}

impl SimulatedDevice {
    /// A device that follows `script` exactly (an infinitely stiff hand).
    pub fn scripted(script: impl FnMut(f64) -> Pose + Send + 'static) -> Self {
        Self {
            script: Box::new(script),
            hand: None,
            limits: DeviceLimits::default(),
            time: 0.0,
            x: Vec3::zeros(),
            v: Vec3::zeros(),
            force: Vec3::zeros(),
            torque: Vec3::zeros(),
            started: false,
        }
    }

    /// The stylus held by `hand`, which aims for the script and feels the
    /// rendered force (the rotation follows the script).
    pub fn with_hand(mut self, hand: SimulatedHand) -> Result<Self> {
        hand.validate()?;
        self.hand = Some(hand);
        Ok(self)
    }

    /// Device limits.
    pub fn with_limits(mut self, limits: DeviceLimits) -> Self {
        self.limits = limits;
        self
    }

    /// The last force and torque rendered.
    pub fn output(&self) -> (Vec3, Vec3) {
        (self.force, self.torque)
    }
}

impl HapticDevice for SimulatedDevice {
    fn pose(&mut self, time: f64) -> Pose {
        let target = (self.script)(time);
        let goal = target.translation.vector;
        match self.hand {
            None => self.x = goal,
            Some(hand) if self.started => {
                // Semi-implicit Euler in substeps of at most 0.1 ms.
                let span = (time - self.time).max(0.0);
                let n = (span / 1e-4).ceil().max(1.0) as usize;
                let dt = span / n as f64;
                for _ in 0..n {
                    let a = (hand.stiffness * (goal - self.x) - hand.damping * self.v + self.force)
                        / hand.mass;
                    self.v += a * dt;
                    self.x += self.v * dt;
                }
            }
            Some(_) => self.x = goal,
        }
        self.started = true;
        self.time = time;
        Isometry3::from_parts(Translation3::from(self.x), target.rotation)
    }

    fn set_output(&mut self, force: Vec3, torque: Vec3) {
        self.force = force;
        self.torque = torque;
    }

    fn limits(&self) -> DeviceLimits {
        self.limits
    }
}
