//! Property tests: arbitrary (often degenerate) input never panics the solver or the file parser.
#![allow(clippy::unwrap_used)]

use std::path::Path;

use cubecal::calib::observations::Observations;
use cubecal::calib::{self, Correspondence, SolveOptions, View};
use nalgebra::{Vector2, Vector3};
use proptest::prelude::*;

fn value() -> impl Strategy<Value = f64> {
    prop_oneof![
        8 => -500.0f64..500.0,
        1 => Just(0.0),
        1 => Just(f64::NAN),
        1 => Just(f64::INFINITY),
        1 => Just(1e300),
    ]
}

fn view() -> impl Strategy<Value = View> {
    proptest::collection::vec((value(), value(), value(), value(), value()), 0..14).prop_map(
        |pts| View {
            name: "v".into(),
            points: pts
                .into_iter()
                .map(|(x, y, z, u, v)| Correspondence {
                    xyz: Vector3::new(x, y, z),
                    uv: Vector2::new(u, v),
                    cov: None,
                })
                .collect(),
        },
    )
}

proptest! {
    #![proptest_config(ProptestConfig { cases: 300, ..ProptestConfig::default() })]

    #[test]
    fn solve_never_panics(views in proptest::collection::vec(view(), 0..3), w in 0u32..2000, h in 0u32..2000) {
        let _ = calib::solve(&views, [w, h], &SolveOptions { max_iterations: 50, ..SolveOptions::default() });
    }

    #[test]
    fn observation_parser_never_panics(text in "\\PC{0,200}") {
        let _ = Observations::from_json(&text, Path::new("fuzz.json"));
    }

    #[test]
    fn observation_parser_never_panics_on_near_valid_json(
        w in proptest::num::i64::ANY, u in proptest::num::f64::ANY, n in 0usize..4
    ) {
        let pts: Vec<String> = (0..n).map(|i| format!("{{\"xyz\": [{i}, {u}, 1], \"uv\": [{u}, 2]}}")).collect();
        let text = format!("{{\"image_size\": [{w}, 10], \"views\": [{{\"points\": [{}]}}]}}", pts.join(","));
        let _ = Observations::from_json(&text, Path::new("fuzz.json"));
    }
}
