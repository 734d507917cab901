//! Seed lists given on the command line.

use crate::{RecipeError, RecipeResult};

/// The most seeds one run takes (a longer `--seeds` range is a typo, not a plan).
pub const MAX_SEEDS: usize = 1000;

/// Parses `0,1,2` (or `0..3`, or one seed) into at most [`MAX_SEEDS`] seeds, each a valid TOML
/// integer (at most `i64::MAX`).
///
/// ```
/// assert_eq!(vdd_recipe::parse_seeds("2..5").unwrap(), [2, 3, 4]);
/// assert_eq!(vdd_recipe::parse_seeds("0,7").unwrap(), [0, 7]);
/// assert!(vdd_recipe::parse_seeds("3..3").is_err());
/// ```
pub fn parse_seeds(s: &str) -> RecipeResult<Vec<u64>> {
    let bad = || RecipeError::InvalidSeeds(s.to_owned());
    let seed = |x: &str| -> RecipeResult<u64> {
        let v: u64 = x.trim().parse().map_err(|_| bad())?;
        if i64::try_from(v).is_err() {
            return Err(RecipeError::SeedTooLarge(v));
        }
        Ok(v)
    };
    let too_many = || RecipeError::TooManySeeds(s.to_owned());
    let seeds: Vec<u64> = if let Some((a, b)) = s.split_once("..") {
        let (a, b) = (seed(a)?, seed(b)?);
        if b.saturating_sub(a) > MAX_SEEDS as u64 {
            return Err(too_many());
        }
        (a..b).collect()
    } else {
        s.split(',').map(seed).collect::<RecipeResult<_>>()?
    };
    if seeds.is_empty() {
        return Err(bad());
    }
    if seeds.len() > MAX_SEEDS {
        return Err(too_many());
    }
    Ok(seeds)
}
