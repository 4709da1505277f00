//! The content-addressed cache.
//!
//! ```text
//! .pipe/
//!   objects/<key>/<table>.parquet   one file per output table
//!   objects/<key>/manifest.json     what made the entry, and each file's size + blake3
//!   tmp/                            entries being written (renamed into objects/ when complete)
//!   trash/                          corrupt entries moved aside for inspection
//!   runs/<stage>.json               the last successful run of each stage instance (for status)
//!   runs/pipelines/<id>.json        each pipeline file that ran here (what gc keeps reachable)
//!   state/verified.json             (size, mtime, inode) of files already hashed, so a no-op
//!                                   run does not re-hash gigabytes
//!   locks/<key>.lock                who computes entry <key> right now (pid, host); see KeyLock
//!   lock                            flock: shared by every `pipe run`, exclusive for `pipe gc`
//! ```
//! An entry is published by writing it completely under `tmp/`, fsyncing it and renaming the
//! directory into `objects/`, so a crash leaves no partial entry. Reading verifies sizes and
//! hashes; a corrupt entry is moved to `trash/` and recomputed.
//!
//! Many `pipe run` processes, on many machines sharing the cache over NFS, may work on one
//! cache at once: before computing an entry a run takes the entry's lock file (created by the
//! hard-link trick, atomic on NFS), then looks again whether another run published the entry
//! meanwhile. The first writer wins; a duplicate is discarded. A lock whose holder died (same
//! host and the pid is gone, or no heartbeat for [`STALE_LOCK_S`]) is broken by the next run.
//!
//! The parts: [`Store`] and its directories (`layout`), entries (`entry`: publish, verify,
//! repair, gc; `pending`: an entry being written, streamed tables included), the Parquet codec
//! (`codec`: written through a hashing writer, read a row group at a time), locks (`locks`),
//! run records (`records`), hash memos (`memo`), file helpers (`files`) and [`StoreError`].

mod codec;
mod entry;
mod error;
mod files;
mod layout;
mod locks;
mod memo;
mod pending;
mod pipelines;
mod records;
mod splice;

pub use codec::{read_parquet, write_parquet, CodecError, StoredTable};
pub use entry::{Entry, InputInfo, Manifest};
pub use error::StoreError;
pub use files::{host_name, unix_now, write_atomic, STALE_LOCK_S};
pub use layout::Store;
pub use locks::{KeyLock, RunLock};
pub use pending::{FileInfo, PendingEntry};
pub use pipelines::KnownPipeline;
pub use records::RunRecord;
