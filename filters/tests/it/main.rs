//! Integration tests of the filters against DSRL's own outputs.

mod filters;
