//! The lens flags' values (`--lens`, `--lens-terms`), and flags given where they do not
//! apply (a recording's flags on a folder of pairs, point mode's on rendered images,
//! ...): one error naming every such flag, so that nothing the user asked for is silently
//! ignored. No degrees of freedom, no units.

use anyhow::{Result, bail};
use headalign::calibrate::LensChoice;
use headalign_geometry::distortion::{DistortionTerms, LensKind};

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
/// estimates none: the flag would be ignored), or ask the equidistant model for the
/// radial-tangential `k3` (`5`: it has four coefficients, and would silently estimate
/// those of `4`).
pub fn check_lens_terms(lens: LensChoice, terms: Option<DistortionTerms>) -> Result<()> {
    if lens == LensChoice::Pinhole && terms.is_some() {
        bail!("--lens-terms needs a lens model to estimate (--lens radtan, equidistant or auto)");
    }
    if lens == LensChoice::Model(LensKind::Equidistant) && terms == Some(DistortionTerms::Full5) {
        bail!(
            "--lens-terms 5 adds the radial-tangential k3; the equidistant model has four coefficients (--lens-terms 4)"
        );
    }
    Ok(())
}

pub fn parse_lens(s: &str) -> Result<LensChoice, String> {
    LensChoice::parse(s)
        .ok_or_else(|| format!("unknown lens model '{s}': pinhole, radtan, equidistant or auto"))
}

pub fn parse_terms(s: &str) -> Result<DistortionTerms, String> {
    DistortionTerms::parse(s).ok_or_else(|| format!("unknown lens terms '{s}': radial, 4 or 5"))
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
