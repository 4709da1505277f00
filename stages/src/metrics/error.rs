//! Why a metric could not be computed, and the input checks every metric shares.

use crate::labels::INSTANCE_FACTOR;
use crate::stage::StageError;

/// Why a metric could not be computed: always a mismatch between inputs, or a bad setting.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum MetricError {
    /// Two maps (or a map and its declared size) have different numbers of pixels.
    #[error(
        "{what} has {got} values, expected {expected} (maps must be width * height, row-major)"
    )]
    Length {
        /// Which input is off, e.g. `"prediction"`.
        what: &'static str,
        expected: usize,
        got: usize,
    },
    /// The class list is unusable (empty, holds the void id 0, or has duplicates).
    #[error("invalid class list: {0}")]
    Classes(String),
    /// Two accumulators built with different settings cannot be merged.
    #[error("cannot merge: {0}")]
    Merge(String),
    /// A numeric setting is out of range.
    #[error("invalid setting: {0}")]
    Setting(String),
}

impl From<MetricError> for StageError {
    fn from(e: MetricError) -> Self {
        match e {
            MetricError::Classes(_) | MetricError::Setting(_) => StageError::Params(e.to_string()),
            _ => StageError::Input(e.to_string()),
        }
    }
}

/// Checks that `got` has `expected` values.
pub(crate) fn check_len(
    what: &'static str,
    expected: usize,
    got: usize,
) -> Result<(), MetricError> {
    if expected == got {
        Ok(())
    } else {
        Err(MetricError::Length {
            what,
            expected,
            got,
        })
    }
}

/// The instance number of a KITTI-360 instance value (`id * 1000 + instance`); values below
/// 1000 (stuff, stored as the bare label id) have instance 0.
pub fn instance_number(value: u32) -> u32 {
    if value >= INSTANCE_FACTOR {
        value % INSTANCE_FACTOR
    } else {
        0
    }
}

/// Checks a class list (non-empty, no 0, no duplicates) and returns the id -> index table
/// (`u16::MAX` for ids not in the list).
pub(crate) fn class_index(classes: &[u8]) -> Result<[u16; 256], MetricError> {
    if classes.is_empty() {
        return Err(MetricError::Classes("the list is empty".into()));
    }
    let mut index = [u16::MAX; 256];
    for (i, &c) in classes.iter().enumerate() {
        if c == crate::labels::UNLABELED {
            return Err(MetricError::Classes(
                "id 0 (unlabeled) is void and cannot be evaluated".into(),
            ));
        }
        if index[c as usize] != u16::MAX {
            return Err(MetricError::Classes(format!("id {c} is listed twice")));
        }
        index[c as usize] = i as u16;
    }
    Ok(index)
}
