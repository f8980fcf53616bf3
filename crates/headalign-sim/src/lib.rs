//! Placeholder: the simulator (filled in by its owner).
