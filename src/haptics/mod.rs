//! Haptic feedback at 1 kHz from the contact compliance.
//!
//! A haptic device needs forces at 500–1000 Hz to feel stiff and stable; the
//! simulation steps at 60 Hz. Because the contact compliance `W` is known,
//! forces can be computed between steps (the scheme of SOFA's
//! `LCPForceFeedback`, done so that every tick iterates):
//!
//! 1. after each step the simulation publishes the tool's contact problem,
//!    linearized in the tool's pose ([`crate::contact::ToolContactProblem`]: `W_TT`, the free
//!    violation `δ_T`, the tool rows `J` of `H`, the pose and the step's
//!    forces; [`crate::contact::ContactSolver::capture_tool`]);
//! 2. the haptic thread takes the newest at each tick and adds `J q` for the
//!    device's motion `q` since that pose;
//! 3. it solves the small friction LCP again, warm-started, within a time
//!    budget ([`HapticSettings::budget`]);
//! 4. it outputs `Jᵀ λ` as force and torque, scaled and clamped to the
//!    device's limits.
//!
//! A virtual coupling (spring–damper, [`Coupling`]) joins the device to the
//! tool the tissue sees (the proxy): the tick solves contact and coupling
//! together (their compliances add in series, [`HapticRenderer`]), the
//! simulation moves the tool to the proxy pose before each step, and the
//! rendered stiffness never exceeds the coupling's.
//!
//! The thread asks for a real-time priority
//! ([`HapticSettings::realtime_priority`]) so that it wakes on time while
//! the simulation keeps every core busy, and runs at normal priority where
//! the system refuses ([`HapticStats::realtime`]).
//!
//! | file | holds |
//! |---|---|
//! | `types.rs` | [`HapticSettings`], [`Coupling`], [`HapticState`], [`HapticStats`] |
//! | `device.rs` | [`HapticDevice`] (where a real device's SDK plugs in), [`SimulatedDevice`], [`SimulatedHand`] |
//! | `render.rs` | [`HapticRenderer`] (one tick, no thread), [`HapticProblem`] |
//! | `thread.rs` | [`HapticLoop`] (the thread, its timing and statistics) |
//! | `mailbox.rs` | [`Mailbox`] (lock-free hand-over of the newest value) |
//!
//! ## Connecting a real device
//! Implement [`HapticDevice`] for a wrapper of the device's SDK: `pose`
//! reads the stylus and maps it into the scene (metres, the scene's frame;
//! scale the workspace there), `set_output` writes the force (and torque,
//! if the device has 6-DoF output) and `limits` gives its maxima. Then
//! [`HapticLoop::start`] with it, or, in Bevy, `HapticsPlugin::new(device,
//! settings)` with a `HapticTool` on the tool entity. The loop never calls
//! the SDK from another thread than its own.
//!
//! ```
//! use bevy_soft_tissue::core_prelude::*;
//! use bevy_soft_tissue::haptics::{HapticLoop, HapticSettings, SimulatedDevice};
//!
//! let mut scene = Scene::new(ContactSettings::default()).unwrap();
//! let mesh = generate::box_mesh(v3(-0.01, -0.01, -0.01), v3(0.01, 0.01, 0.0), [4, 4, 2]).unwrap();
//! let mut block = DeformableBody::new(mesh, TissueMaterial::new(1000.0, 3e3, 0.4), BodySettings::default()).unwrap();
//! block.fix_where(|p| p.z < -0.0099);
//! scene.add_body(block);
//! let at = |z: f64| Pose::translation(0.0, 0.0, z);
//! let tool = scene.add_tool(RigidTool::new(ToolShape::Sphere { radius: 0.004 }, at(0.004)).unwrap());
//! scene.contact.capture_tool(Some(tool));
//! // A stylus pressed 1 mm into the block.
//! let device = SimulatedDevice::scripted(move |_| at(0.003));
//! let mut haptics = HapticLoop::start(device, HapticSettings::default()).unwrap();
//! for _ in 0..5 {
//!     let proxy = haptics.poll().proxy;
//!     scene.tools[tool].set_pose(proxy).unwrap();
//!     scene.step(1.0 / 60.0).unwrap();
//!     haptics.publish(scene.contact.tool_problem());
//!     std::thread::sleep(std::time::Duration::from_millis(5));
//! }
//! haptics.stop().unwrap();
//! ```

mod device;
mod mailbox;
mod render;
mod thread;
mod types;

pub use device::{DeviceLimits, HapticDevice, Script, SimulatedDevice, SimulatedHand};
pub use mailbox::Mailbox;
pub use render::{HapticProblem, HapticRenderer, TickOutput};
pub use thread::HapticLoop;
pub use types::{Coupling, HapticSettings, HapticState, HapticStats};
