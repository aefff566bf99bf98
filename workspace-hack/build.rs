// Cargo builds build-dependencies only for a package with a build script: this one pins the
// features of the proc-macro side (syn) and does nothing else.
fn main() {}
