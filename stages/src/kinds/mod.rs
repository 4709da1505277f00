//! Every stage kind, one module each, named after the kind, and the registry the runner looks
//! them up in. A kind is glue between tables and the library below; it never imports another
//! kind.

pub mod registry;
