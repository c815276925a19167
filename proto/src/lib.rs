//! gRPC contracts of the dsrl service. The `.proto` files under `dsrl/` are the source; the Rust code under
//! `src/gen/` is generated from them and committed, so building needs no protoc. `tests/codegen.rs` regenerates
//! it into a temporary directory and fails on any drift (`DSRL_UPDATE_CODEGEN=1` rewrites it instead).

pub mod datasets {
    pub mod v1 {
        include!("gen/dsrl.datasets.v1.rs");
    }
}

pub mod leaderboard {
    pub mod v1 {
        include!("gen/dsrl.leaderboard.v1.rs");
    }
}

pub mod simulator {
    pub mod v1 {
        include!("gen/dsrl.simulator.v1.rs");

        /// The most maps an `Idm` controller may draw its episodes from (DSRL's collection used 10): MetaDrive
        /// builds and keeps every map a session draws from. Workers refuse more; recipes are checked against it.
        pub const MAX_IDM_MAPS: u32 = 100;
    }
}

pub mod tensor;
