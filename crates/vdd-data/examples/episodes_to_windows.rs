//! Episodes → `.npz` → windows and chunks → normalisation, the data side of training.
//!
//! ```text
//! cargo run -p vdd-data --example episodes_to_windows
//! ```
//!
//! Builds a few ragged episodes of a 2-D point walking towards a goal, saves them as an `.npz`
//! archive in a temporary directory (the layout numpy's `np.load` reads), loads them back, fits
//! a normalisation on a training split and cuts observation windows and action chunks. No
//! network, nothing written outside the temporary directory.

use faer::Mat;
use vdd_data::{Episodes, Normalization, NormalizationKind, SequenceDataset, WindowConfig};

fn main() -> Result<(), Box<dyn std::error::Error>> {
    // Twelve episodes of 10 to 21 steps: observation = position, action = step towards (1, 1).
    let (mut observations, mut actions) = (Vec::new(), Vec::new());
    for i in 0..12 {
        let len = 10 + i;
        let start = [i as f32 * 0.1, 1.0 - i as f32 * 0.05];
        let pos = |t: usize, j: usize| start[j] + (1.0 - start[j]) * t as f32 / len as f32;
        observations.push(Mat::from_fn(len, 2, pos));
        actions.push(Mat::from_fn(len, 2, |t, j| pos(t + 1, j) - pos(t, j)));
    }
    let episodes = Episodes::from_episodes(observations, actions)?;

    // Save and load back: every float bit-identical.
    let dir = std::env::temp_dir().join(format!("vdd-data-example-{}", std::process::id()));
    std::fs::create_dir_all(&dir)?;
    let path = dir.join("walks.npz");
    episodes.save_npz(&path)?;
    let loaded = Episodes::load_npz(&path)?;
    assert_eq!(loaded, episodes);
    println!(
        "{} episodes, {} steps in all (longest {}), saved to and loaded from {}",
        loaded.num_episodes(),
        loaded.num_steps(),
        loaded.max_len(),
        path.display()
    );

    // Split by episode; the normalisation sees the training episodes only.
    let split = loaded.split(0.25, 0)?;
    let norm = Normalization::fit(&split.train, NormalizationKind::standard())?;
    println!(
        "observation offset {:?}, scale {:?}",
        norm.observations.offset, norm.observations.scale
    );

    // Windows of 2 observations, chunks of 3 actions.
    let train = SequenceDataset::new(split.train.normalized(&norm)?, WindowConfig::new(2, 3))?;
    let (states, chunks) = train.to_matrices();
    println!(
        "{} training samples: states {} x {}, action chunks {} x {}",
        train.len(),
        states.nrows(),
        states.ncols(),
        chunks.nrows(),
        chunks.ncols()
    );
    println!(
        "first state (2 normalised observations): {:?}",
        (0..4).map(|j| states[(0, j)]).collect::<Vec<_>>()
    );
    std::fs::remove_dir_all(&dir)?;
    Ok(())
}
