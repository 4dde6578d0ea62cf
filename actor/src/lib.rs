//! Crate root; its contents arrive with the issue that builds this crate.
