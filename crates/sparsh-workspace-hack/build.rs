//! Present so that cargo applies the crate's build dependencies (their features unify the build
//! scripts' and proc-macros' dependencies too).
fn main() {}
