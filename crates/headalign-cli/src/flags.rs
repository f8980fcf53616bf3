//! The scenario flags of `demo` and `simulate` ([`ScenarioArgs`]), the lens flags'
//! values (`--lens`, `--lens-terms`), and flags given where they do not
//! apply (a recording's flags on a folder of pairs, point mode's on rendered images,
//! ...): one error naming every such flag, so that nothing the user asked for is silently
//! ignored. No degrees of freedom, no units.

use std::path::PathBuf;

use anyhow::{Context, Result, bail};
use clap::Args;
use headalign::calibrate::LensChoice;
use headalign_geometry::distortion::DistortionTerms;
use headalign_geometry::lens::MODELS;
use headalign_sim::Scenario;

/// An error naming each flag of `given` (flag, whether given) that was given: "`--a, --b`
/// apply only to `only_to`"; nothing when none was.
pub fn refuse(given: &[(&str, bool)], only_to: &str) -> Result<()> {
    let names: Vec<&str> = given.iter().filter_map(|&(flag, on)| on.then_some(flag)).collect();
    match names.as_slice() {
        [] => Ok(()),
        [one] => bail!("{one} applies only to {only_to}"),
        many => bail!("{} apply only to {only_to}", many.join(", ")),
    }
}

/// An error when `--lens-terms` come without a lens model to estimate (the pinhole
/// estimates none: the flag would be ignored), or ask a model for a level of terms that
/// adds none to the level before while the model has levels (the equidistant model's `5`:
/// it has four coefficients, and would silently estimate those of `4`).
pub fn check_lens_terms(lens: LensChoice, terms: Option<DistortionTerms>) -> Result<()> {
    if lens == LensChoice::Pinhole && terms.is_some() {
        let estimated: Vec<&str> =
            MODELS.iter().filter(|m| !m.param_names().is_empty()).map(|m| m.names().short).collect();
        bail!("--lens-terms needs a lens model to estimate (--lens {} or auto)", estimated.join(", "));
    }
    if let (Some(kind), Some(terms)) = (lens.kind(), terms) {
        let m = kind.model();
        let levels = DistortionTerms::LEVELS;
        let below = levels.iter().rev().find(|t| t.count() < terms.count());
        let nested = m.estimated(DistortionTerms::Radial2) < m.param_names().len();
        if let Some(&below) = below
            && nested
            && m.estimated(terms) == m.estimated(below)
        {
            bail!(
                "--lens-terms {} adds no coefficient to the {} model, which has {} ({}; --lens-terms {})",
                terms.count(),
                m.names().short,
                m.param_names().len(),
                m.param_names().join(" "),
                below.count()
            );
        }
    }
    Ok(())
}

/// The short names of the lens table's models (`--lens`).
fn model_names() -> Vec<&'static str> {
    MODELS.iter().map(|m| m.names().short).collect()
}

pub fn parse_lens(s: &str) -> Result<LensChoice, String> {
    LensChoice::parse(s)
        .ok_or_else(|| format!("unknown lens model '{s}': {}, or auto", model_names().join(", ")))
}

pub fn parse_terms(s: &str) -> Result<DistortionTerms, String> {
    DistortionTerms::parse(s).ok_or_else(|| format!("unknown lens terms '{s}': radial, 4 or 5"))
}

#[derive(Args, Clone)]
pub struct ScenarioArgs {
    /// Random seed of the scenario (head errors, scene, noise).
    #[arg(long, default_value_t = 1)]
    seed: u64,
    /// Image noise, pixels (standard deviation per coordinate).
    #[arg(long)]
    noise: Option<f64>,
    /// Number of scene points seen by both cameras in the initial view.
    #[arg(long)]
    points: Option<usize>,
    /// Fraction of observations replaced by outliers (0 to <1).
    #[arg(long)]
    outliers: Option<f64>,
    /// Rotation of the elevation, pan and vergence moves, degrees.
    #[arg(long)]
    rotation: Option<f64>,
    /// Scenario file (TOML) overriding the defaults; flags override the file.
    #[arg(long, conflicts_with = "scene")]
    scenario: Option<PathBuf>,
    /// Scene preset instead of the default room: `default`, `paper`, `robot`, `wall` (one
    /// plane 1-4 m ahead) or `far` (200-800 m); flags override it.
    // Resolved by `Scenario::preset`, as `experiment --scene`.
    #[arg(long)]
    scene: Option<String>,
}

impl ScenarioArgs {
    /// An error naming the point-mode flags (`--noise`, `--points`, `--outliers`) when the
    /// run renders images instead: the front end finds its own points there, and the
    /// flags would be ignored.
    pub fn refuse_point_mode_flags(&self) -> Result<()> {
        refuse(
            &[
                ("--noise", self.noise.is_some()),
                ("--points", self.points.is_some()),
                ("--outliers", self.outliers.is_some()),
            ],
            "point mode; with --images the scene is rendered and the front end finds its own points (the images' noise: render.noise_sigma_grey in a --scenario file)",
        )
    }

    pub fn scenario(&self) -> Result<Scenario> {
        let mut s = match &self.scenario {
            Some(path) => {
                let text = std::fs::read_to_string(path)
                    .with_context(|| format!("cannot read {}", path.display()))?;
                Scenario::from_toml_str(&text).map_err(|e| anyhow::anyhow!("{}: {e}", path.display()))?
            }
            None => match &self.scene {
                Some(name) => Scenario::preset(name).map_err(|e| anyhow::anyhow!("--scene: {e}"))?,
                None => Scenario::default(),
            },
        };
        s.seed = self.seed;
        if let Some(v) = self.noise {
            s.noise_px = v;
        }
        if let Some(v) = self.points {
            s.points = v;
        }
        if let Some(v) = self.outliers {
            s.outlier_fraction = v;
        }
        if let Some(v) = self.rotation {
            s.rotation_deg = v;
        }
        s.validate()?;
        Ok(s)
    }
}

#[cfg(test)]
mod tests {
    use super::refuse;

    #[test]
    fn names_every_given_flag_and_agrees_in_number() {
        assert!(refuse(&[("--a", false)], "x").is_ok());
        let one = refuse(&[("--a", false), ("--b", true)], "images").unwrap_err().to_string();
        assert_eq!(one, "--b applies only to images");
        let two = refuse(&[("--a", true), ("--b", true)], "images").unwrap_err().to_string();
        assert_eq!(two, "--a, --b apply only to images");
    }
}
