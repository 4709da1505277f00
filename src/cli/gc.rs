//! `pipe gc`: removes the entries that no pipeline file known to the cache reaches. A cache is
//! often shared (a matrix, several sequences, a colleague's runs), so what the `-f` pipeline
//! does not reach may be another pipeline's work: every pipeline file that ran in the cache is
//! resolved as it stands now, and one that cannot be read or resolved here (its data is on
//! another machine) keeps what its last run reached.

use std::{
    collections::BTreeSet,
    path::{Path, PathBuf},
};

use crate::{
    config::{self, Pipeline},
    dag::Dag,
    runner::{self, State},
    store::{unix_now, RunLock, Store, StoreError},
};

/// Why `pipe gc` could not do its work.
#[derive(Debug, thiserror::Error)]
pub enum GcError {
    #[error(transparent)]
    Config(#[from] config::ConfigError),
    #[error(transparent)]
    Run(#[from] runner::RunError),
    #[error(transparent)]
    Store(#[from] StoreError),
    #[error("stage `{stage}` reads {}, which is not here", .file.display())]
    NotHere { stage: String, file: PathBuf },
    #[error("the cache at {} is read-only ({why}): nothing can be removed", .cache.display())]
    ReadOnly { cache: PathBuf, why: String },
}

/// What `pipe gc` was asked.
pub struct GcOptions {
    pub keep_all_runs: bool,
    pub dry_run: bool,
    /// Keep only what the `-f` pipeline reaches, whatever else ran in the cache.
    pub only_this_pipeline: bool,
}

/// The entries `p` reaches in `store` as its files stand now.
fn reached(p: &Pipeline, store: &Store) -> Result<BTreeSet<String>, GcError> {
    let dag = Dag::build(p)?;
    Ok(runner::resolve(p, &dag, store, false)?
        .into_iter()
        .filter(|r| matches!(r.state, State::Fresh(_)))
        .filter_map(|r| r.key)
        .collect())
}

pub fn run(p: &Pipeline, opts: &GcOptions) -> Result<i32, GcError> {
    let store = Store::open(&p.cache_dir)?;
    if let Some(why) = store.read_only() {
        return Err(GcError::ReadOnly {
            cache: p.cache_dir.clone(),
            why: why.to_string(),
        });
    }
    let _lock = RunLock::acquire(store.root(), false, true)?;
    let mut keep = reached(p, &store)?;
    println!("{}: reaches {} entries", p.file.display(), keep.len());
    if !opts.only_this_pipeline {
        let this = std::fs::canonicalize(&p.file).ok();
        for known in store.known_pipelines() {
            if Some(&known.file) == this.as_ref() {
                continue;
            }
            let file = known.file.display();
            // Its data may not be here (a colleague's machine): then what its last run reached.
            let resolved = other_pipeline(&known.file, p)
                .map_err(GcError::from)
                .and_then(|q| inputs_here(&q).map(|()| q))
                .and_then(|q| reached(&q, &store));
            match resolved {
                Ok(keys) => {
                    println!(
                        "{file}: reaches {} entries (it ran in this cache)",
                        keys.len()
                    );
                    keep.extend(keys);
                }
                Err(e) => {
                    let kept: Vec<&String> = known
                        .keys
                        .iter()
                        .filter(|k| store.entry_dir(k).is_dir())
                        .collect();
                    println!(
                        "{file}: cannot be read or resolved here ({e}); keeping the {} entries \
                         its last run on {} reached ({})",
                        kept.len(),
                        known.host,
                        ago(known.last_run)
                    );
                    keep.extend(kept.into_iter().cloned());
                }
            }
        }
    }
    if opts.keep_all_runs {
        for rec in store.run_records().into_values() {
            keep.extend(rec.history);
            keep.insert(rec.key);
        }
    }
    // Described before anything is removed (the manifests go with the entries).
    let removed = store.gc(&keep, true)?;
    for (key, bytes) in &removed {
        let what = store.manifest_of(key).map_or_else(
            || "(no readable manifest)".to_string(),
            |m| {
                format!(
                    "stage `{}` ({} v{}), made {}",
                    m.stage,
                    m.kind,
                    m.version,
                    ago(m.finished)
                )
            },
        );
        println!(
            "  {} {:>10}  {what}",
            &key[..key.len().min(16)],
            runner::fmt_bytes(*bytes)
        );
    }
    if !opts.dry_run {
        store.gc(&keep, false)?;
    }
    let total: u64 = removed.iter().map(|(_, b)| b).sum();
    println!(
        "{} {} entries ({}), kept {}{}",
        if opts.dry_run {
            "would remove"
        } else {
            "removed"
        },
        removed.len(),
        runner::fmt_bytes(total),
        store.keys().len() - if opts.dry_run { removed.len() } else { 0 },
        if opts.only_this_pipeline || removed.is_empty() {
            ""
        } else {
            " (what no pipeline known to the cache reaches; `--only-this-pipeline` removes \
             every other pipeline's entries too)"
        }
    );
    Ok(0)
}

/// Whether every file outside the cache that `q`'s stages read is here: if one is missing, what
/// `q` reaches cannot be known on this machine.
fn inputs_here(q: &Pipeline) -> Result<(), GcError> {
    for s in &q.stages {
        let paths = s.kind.external_inputs(&s.params).map_err(|source| {
            runner::RunError::ExternalInputs {
                stage: s.name.clone(),
                source,
            }
        })?;
        if let Some(missing) = paths.iter().find(|f| !f.exists()) {
            return Err(GcError::NotHere {
                stage: s.name.clone(),
                file: missing.clone(),
            });
        }
    }
    Ok(())
}

/// Another pipeline file known to the cache, read as it stands, on this cache.
fn other_pipeline(file: &Path, this: &Pipeline) -> Result<Pipeline, config::ConfigError> {
    let mut q = config::load(file, &[])?;
    q.cache_dir = this.cache_dir.clone();
    Ok(q)
}

/// "3 h ago" for a time in seconds since the epoch.
fn ago(t: f64) -> String {
    let s = (unix_now() - t).max(0.0);
    match s {
        s if s < 120.0 => format!("{s:.0} s ago"),
        s if s < 7200.0 => format!("{:.0} min ago", s / 60.0),
        s if s < 172_800.0 => format!("{:.0} h ago", s / 3600.0),
        s => format!("{:.0} days ago", s / 86400.0),
    }
}
