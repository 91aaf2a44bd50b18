//! # transport: how lungdyn's payloads travel, and the loop machinery around it
//!
//! The protocol (the payloads, their layouts and version) is `ipc-types`; this crate moves those
//! payloads and paces the loops that consume them:
//!
//! * [`port`] — the [`Publish`]/[`Receive`] traits every process loop is written against, with typed
//!   [`PortError`]s;
//! * [`iox`] — the product implementation over iceoryx2 zero-copy shared memory ([`iox::Outlet`],
//!   [`iox::Inlet`]);
//! * [`memory`] — in-memory ports on a fake clock, the test doubles of a stream;
//! * [`clock`] — the monotonic clock and its fake;
//! * [`pacer`] — wake on a sample, fall back to an absolute deadline: the one timing rule of the
//!   engine and renderer loops;
//! * [`instance`] — one run's stream names and the files it leaves behind;
//! * [`process`] — common process options (validated `--seconds`), pinning, error printing;
//! * [`realtime`] — SCHED_FIFO and locked memory where permitted, a warning naming the limit where not;
//! * [`trace`] — stage spans in a bounded ring per process, merged into one Chrome/Perfetto trace;
//! * [`wake`] — how a receiver waits: the event, spin-then-park or busy-poll, chosen from the cores.
//!
//! Nothing here calls iceoryx2's `testing` module.

pub mod clock;
pub mod instance;
pub mod iox;
pub mod memory;
pub mod notify;
pub mod pacer;
pub mod port;
pub mod process;
pub mod realtime;
pub mod stop;
pub mod trace;
pub mod wake;

pub use clock::{now_ns, Clock, FakeClock, Monotonic};
pub use instance::{Cleanup, Instance, RunningInstance, RunningProcess};
pub use pacer::{Pacer, PacerConfig, Tick, Wake};
pub use port::{PortError, Publish, Receive};
