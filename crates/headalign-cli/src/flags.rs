//! Flags given where they do not apply (a recording's flags on a folder of pairs, point
//! mode's on rendered images, ...): one error naming every such flag, so that nothing the
//! user asked for is silently ignored. No degrees of freedom, no units.

use anyhow::{Result, bail};

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
