//! Shared helpers of the renderer's integration tests: the fixture scenes and image comparison.
//!
//! The scenes live in `models/fixtures/scenes/<name>.safetensors` (written by
//! `python -m c4g.raster.scenes`; layout and contents in that folder's README.md): Gaussian
//! parameters, a camera, a background and the float64 reference's render of them (stored as f32)
//! with the footprint the metadata names (`footprint`; absent: the ellipse).
#![allow(dead_code, clippy::unwrap_used, clippy::expect_used)]

use std::path::PathBuf;

use c4g_renderer::{FeatureImage, Image, RenderOptions};
use c4g_scene::Footprint;
use c4g_scene::{Camera, FeatureBlock, GaussianSet, Intrinsics};
use glam::Mat4;
use safetensors::{Dtype, SafeTensors};

/// Every fixture scene rendered with the ellipse footprint, by name.
pub const SCENES: [&str; 6] = [
    "cloud",
    "extremes",
    "fullscreen",
    "stack",
    "background",
    "large",
];

/// The same scenes rendered with the 3DGS footprint (each kept with its own seed).
pub const SCENES_3DGS: [&str; 6] = [
    "cloud-3dgs",
    "extremes-3dgs",
    "fullscreen-3dgs",
    "stack-3dgs",
    "background-3dgs",
    "large-3dgs",
];

/// One fixture scene: what to render and what the reference rendered.
#[derive(Debug, Clone)]
pub struct Scene {
    pub gaussians: GaussianSet,
    pub camera: Camera,
    pub options: RenderOptions,
    pub expected: Image,
}

/// The largest differences between two images.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Diff {
    pub rgb_max_abs: f32,
    pub alpha_max_abs: f32,
    /// Relative difference of the alpha-weighted depth, over pixels where the expected alpha > 0.5.
    pub depth_max_rel_where_alpha_gt_half: f32,
    /// The same for the expected depth.
    pub expected_depth_max_rel_where_alpha_gt_half: f32,
    /// 0 when neither image has features, infinite when only one has or their widths differ.
    pub features_max_abs: f32,
}

impl Diff {
    /// The tolerance every rasterizer is held to against the float64 reference: RGB, alpha and
    /// features within 2e-3 absolute, depths within 1e-3 relative where alpha > 0.5.
    pub fn assert_within_reference_tolerance(&self, name: &str) {
        let d = self;
        assert!(d.rgb_max_abs <= 2e-3, "{name}: {d:?}");
        assert!(d.alpha_max_abs <= 2e-3, "{name}: {d:?}");
        assert!(d.features_max_abs <= 2e-3, "{name}: {d:?}");
        assert!(d.depth_max_rel_where_alpha_gt_half <= 1e-3, "{name}: {d:?}");
        assert!(
            d.expected_depth_max_rel_where_alpha_gt_half <= 1e-3,
            "{name}: {d:?}"
        );
    }
}

pub fn workspace() -> PathBuf {
    // `C4G_WORKSPACE`: a test binary run away from the checkout it was built in
    // (scripts/device-check carries it to a GPU machine with the repository).
    std::env::var_os("C4G_WORKSPACE")
        .map(PathBuf::from)
        .unwrap_or_else(|| PathBuf::from(env!("CARGO_MANIFEST_DIR")).join(".."))
}

pub fn scenes_dir() -> PathBuf {
    workspace().join("models/fixtures/scenes")
}

/// Loads `models/fixtures/scenes/<name>.safetensors`.
pub fn load_scene(name: &str) -> Scene {
    let path = scenes_dir().join(format!("{name}.safetensors"));
    let bytes = std::fs::read(&path).unwrap_or_else(|e| panic!("{}: {e}", path.display()));
    let st = SafeTensors::deserialize(&bytes).unwrap();
    let f = |key: &str| floats(&st, key);
    let (_, header) = SafeTensors::read_metadata(&bytes).unwrap();
    let footprint = match header
        .metadata()
        .as_ref()
        .and_then(|m| m.get("footprint"))
        .map(String::as_str)
    {
        None | Some("ellipse") => Footprint::Ellipse,
        Some("3dgs") => Footprint::Tiles3dgs,
        Some(other) => panic!("{}: unknown footprint {other:?}", path.display()),
    };

    let size = f("size");
    let (width, height) = (size[0] as u32, size[1] as u32);
    let k = f("intrinsics");
    let intrinsics = Intrinsics {
        fx: k[0],
        fy: k[1],
        cx: k[2],
        cy: k[3],
        width,
        height,
    };
    let view = f("world_to_camera");
    // Row-major on disk; glam builds from columns.
    let view = Mat4::from_cols_slice(&view).transpose();
    let camera = Camera::from_world_to_camera_matrix(intrinsics, view).unwrap();

    let mut gaussians = GaussianSet::new(
        triples(&f("positions")),
        triples(&f("scales")),
        f("rotations")
            .chunks_exact(4)
            .map(|q| [q[0], q[1], q[2], q[3]])
            .collect(),
        f("opacities"),
        triples(&f("colors")),
    )
    .unwrap();
    let mut features = None;
    if st.names().contains(&"features") {
        let channels = st.tensor("features").unwrap().shape()[1];
        gaussians = gaussians
            .with_features(FeatureBlock::new(channels, f("features")).unwrap())
            .unwrap();
        features = Some(FeatureImage {
            channels,
            values: f("features_image"),
        });
    }
    let bg = f("background");
    let options = RenderOptions {
        background: [bg[0], bg[1], bg[2]],
        footprint,
        ..RenderOptions::default()
    };
    let expected = Image {
        width,
        height,
        rgb: f("rgb"),
        alpha: f("alpha"),
        depth: f("depth"),
        expected_depth: f("expected_depth"),
        features,
    };
    Scene {
        gaussians,
        camera,
        options,
        expected,
    }
}

/// The largest differences of `got` from `expected` (sizes must match).
pub fn compare(got: &Image, expected: &Image) -> Diff {
    assert_eq!(
        (got.width, got.height),
        (expected.width, expected.height),
        "image sizes differ"
    );
    let max_abs = |a: &[f32], b: &[f32]| {
        assert_eq!(a.len(), b.len());
        a.iter()
            .zip(b)
            .map(|(x, y)| if x == y { 0.0 } else { (x - y).abs() })
            .fold(0.0f32, |m, d| if d.is_nan() { f32::NAN } else { m.max(d) })
    };
    let rel_where_opaque = |a: &[f32], b: &[f32]| {
        let mut worst = 0.0f32;
        for ((x, y), alpha) in a.iter().zip(b).zip(&expected.alpha) {
            if *alpha > 0.5 {
                let d = (x - y).abs() / y.abs().max(f32::MIN_POSITIVE);
                worst = if d.is_nan() { f32::NAN } else { worst.max(d) };
            }
        }
        worst
    };
    let features_max_abs = match (&got.features, &expected.features) {
        (None, None) => 0.0,
        (Some(g), Some(e)) if g.channels == e.channels => max_abs(&g.values, &e.values),
        _ => f32::INFINITY,
    };
    Diff {
        rgb_max_abs: max_abs(&got.rgb, &expected.rgb),
        alpha_max_abs: max_abs(&got.alpha, &expected.alpha),
        depth_max_rel_where_alpha_gt_half: rel_where_opaque(&got.depth, &expected.depth),
        expected_depth_max_rel_where_alpha_gt_half: rel_where_opaque(
            &got.expected_depth,
            &expected.expected_depth,
        ),
        features_max_abs,
    }
}

/// A tensor as f32 values, whatever its stored dtype (f32, f64, i32, i64).
fn floats(st: &SafeTensors, key: &str) -> Vec<f32> {
    let t = st
        .tensor(key)
        .unwrap_or_else(|e| panic!("tensor {key}: {e}"));
    let data = t.data();
    match t.dtype() {
        Dtype::F32 => data
            .chunks_exact(4)
            .map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]]))
            .collect(),
        Dtype::I32 => data
            .chunks_exact(4)
            .map(|b| i32::from_le_bytes([b[0], b[1], b[2], b[3]]) as f32)
            .collect(),
        Dtype::F64 => data
            .chunks_exact(8)
            .map(|b| f64::from_le_bytes(b.try_into().unwrap()) as f32)
            .collect(),
        Dtype::I64 => data
            .chunks_exact(8)
            .map(|b| i64::from_le_bytes(b.try_into().unwrap()) as f32)
            .collect(),
        other => panic!("tensor {key}: unsupported dtype {other:?}"),
    }
}

fn triples(v: &[f32]) -> Vec<[f32; 3]> {
    v.chunks_exact(3).map(|c| [c[0], c[1], c[2]]).collect()
}

/// A camera at the origin looking down +z, principal point at the image centre.
pub fn camera(width: u32, height: u32, focal: f32) -> Camera {
    Camera::new(
        Intrinsics {
            fx: focal,
            fy: focal,
            cx: width as f32 / 2.0,
            cy: height as f32 / 2.0,
            width,
            height,
        },
        glam::Affine3A::IDENTITY,
    )
    .unwrap()
}

/// An unrotated Gaussian: position, scale, opacity, colour.
pub type Plain = ([f32; 3], [f32; 3], f32, [f32; 3]);

/// One unrotated Gaussian per tuple.
pub fn set_of(gaussians: &[Plain]) -> GaussianSet {
    GaussianSet::new(
        gaussians.iter().map(|g| g.0).collect(),
        gaussians.iter().map(|g| g.1).collect(),
        vec![[1.0, 0.0, 0.0, 0.0]; gaussians.len()],
        gaussians.iter().map(|g| g.2).collect(),
        gaussians.iter().map(|g| g.3).collect(),
    )
    .unwrap()
}

/// `n` random Gaussians in front of the origin camera, `spread` wide at depth 2..6, sizes
/// `size` (world units), seeded.
pub fn random_set(n: usize, seed: u64, spread: f32, size: f32) -> GaussianSet {
    let mut rng = SplitMix(seed);
    let mut set = (Vec::new(), Vec::new(), Vec::new(), Vec::new(), Vec::new());
    for _ in 0..n {
        let z = 2.0 + 4.0 * rng.unit();
        set.0.push([
            spread * (rng.unit() - 0.5) * z,
            spread * (rng.unit() - 0.5) * z,
            z,
        ]);
        set.1.push([
            size * (0.3 + rng.unit()),
            size * (0.3 + rng.unit()),
            size * (0.3 + rng.unit()),
        ]);
        let q = [
            rng.unit() - 0.5,
            rng.unit() - 0.5,
            rng.unit() - 0.5,
            rng.unit() - 0.5,
        ];
        let norm = q.iter().map(|v| v * v).sum::<f32>().sqrt().max(1e-3);
        set.2.push(q.map(|v| v / norm));
        set.3.push(0.1 + 0.9 * rng.unit());
        set.4.push([rng.unit(), rng.unit(), rng.unit()]);
    }
    GaussianSet::new(set.0, set.1, set.2, set.3, set.4).unwrap()
}

/// A small deterministic generator (SplitMix64), so tests need no RNG crate.
pub struct SplitMix(pub u64);

impl SplitMix {
    pub fn next_u64(&mut self) -> u64 {
        self.0 = self.0.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        z ^ (z >> 31)
    }

    /// Uniform in [0, 1).
    pub fn unit(&mut self) -> f32 {
        (self.next_u64() >> 40) as f32 / (1u64 << 24) as f32
    }
}

/// Asserts every plane of the image is finite.
pub fn assert_finite(image: &Image) {
    assert!(image.rgb.iter().all(|v| v.is_finite()), "rgb not finite");
    assert!(
        image.alpha.iter().all(|v| v.is_finite()),
        "alpha not finite"
    );
    assert!(
        image.depth.iter().all(|v| v.is_finite()),
        "depth not finite"
    );
    assert!(
        image.expected_depth.iter().all(|v| v.is_finite()),
        "expected depth not finite"
    );
    if let Some(f) = &image.features {
        assert!(
            f.values.iter().all(|v| v.is_finite()),
            "features not finite"
        );
    }
}
