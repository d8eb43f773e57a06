//! nerflabel: turn a handheld RGB-D scan into training data for object
//! detectors and segmenters with a depth-supervised NeRF fitted on the CPU.
//!
//! Data flows `scan` (read any layout into one [`scan::Scan`]) -> `poses`
//! (bounds, normalisation, geometry) -> `nerf` (fit and render) -> `boxes`
//! (3D boxes to labels) -> `synth` (novel views to Parquet). `fixture` is the
//! project's own procedural scene generator with exact ground truth.
//! The library never prints; the CLI in `main.rs` owns all output.

pub mod annotate;
pub mod atomic;
pub mod batch;
pub mod boxes;
pub mod evaluate;
pub mod fixture;
pub mod mask;
pub mod masks;
pub mod nerf;
pub mod outputs;
pub mod plot;
pub mod png_encode;
pub mod poses;
pub mod rng;
pub mod scan;
pub mod synth;

/// The names an option enum takes on the command line, for error messages
/// of the library's own parsers (`native, tum, ...`): the same list `--help`
/// shows, from the one `clap::ValueEnum` declaration.
pub fn value_names<T: clap::ValueEnum>() -> String {
    let names: Vec<String> = T::value_variants()
        .iter()
        .filter_map(|v| v.to_possible_value())
        .map(|v| v.get_name().to_string())
        .collect();
    names.join(", ")
}

#[cfg(test)]
mod tests {
    use clap::ValueEnum;

    /// `name()` (outputs, meta files) and the command line spell every value alike.
    fn spelled_alike<T: ValueEnum + Copy + std::fmt::Debug>(name: fn(T) -> &'static str) {
        for v in T::value_variants() {
            let value = v.to_possible_value().unwrap_or_else(|| panic!("{v:?} is skipped"));
            assert_eq!(value.get_name(), name(*v), "{v:?}");
            assert!(T::from_str(&name(*v).to_uppercase(), true).is_ok());
        }
    }

    #[test]
    fn option_enums_have_one_spelling_for_names_and_flags() {
        spelled_alike(crate::scan::Layout::name);
        spelled_alike(crate::fixture::SceneKind::name);
        spelled_alike(crate::fixture::FixtureLayout::name);
        spelled_alike(crate::boxes::DepthSource::name);
        spelled_alike(crate::boxes::Overlap::name);
        assert_eq!(super::value_names::<crate::boxes::Overlap>(), "smallest, deepest");
    }
}
