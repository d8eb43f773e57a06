//! Small fully connected networks.
