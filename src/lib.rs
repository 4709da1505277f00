//! The `pipe` runner: loads `pipeline.yaml`, builds the stage graph, keys every stage by content
//! and runs what is stale, caching outputs as verified Parquet entries. It knows stage kinds only
//! through the `stages` crate's registry and nothing about NeRFs.
//!
//! The modules, each using only those listed before it: [`error`] (what every error shares),
//! [`fingerprint`] (cache keys), [`config`] (the pipeline file), [`dag`], [`store`] (the
//! cache), [`runner`] (plan, schedule and execute a run), [`executor`] (scenes as worker
//! processes or a Slurm array), [`bench`] (suites of runs and their report), [`cli`].

pub mod bench;
pub mod cli;
pub mod config;
pub mod dag;
pub mod error;
pub mod executor;
pub mod fingerprint;
pub mod runner;
pub mod store;
