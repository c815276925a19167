//! Integration tests of the dataset formats: canonical Parquet, foreign Parquet layouts, DSRL HDF5.
mod formats;
