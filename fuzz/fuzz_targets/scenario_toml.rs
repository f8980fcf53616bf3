//! Fuzz the scenario reader (`headalign_sim::Scenario::from_toml_str`, what `demo
//! --scenario FILE` reads): any text gives a validated scenario or an error. A scenario
//! that validates must write back to TOML and read back equal.
#![no_main]

use headalign_sim::Scenario;
use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    let Ok(text) = std::str::from_utf8(data) else { return };
    let Ok(s) = Scenario::from_toml_str(text) else { return };
    let back = s.to_toml_string().expect("a valid scenario serialises");
    let again = Scenario::from_toml_str(&back).expect("round trip parses");
    assert_eq!(again, s, "round trip changed the scenario");
});
