//! The `pipe` runner: loads `pipeline.yaml`, builds the stage graph, keys every stage by content
//! and runs what is stale, caching outputs as verified Parquet entries. It knows stage kinds only
//! through the `stages` crate's registry and nothing about NeRFs.

pub mod bench;
pub mod cli;
pub mod config;
pub mod dag;
pub mod executor;
pub mod fingerprint;
pub mod runner;
pub mod store;
