//! Shared harness for end-to-end tests across real bcal processes.
