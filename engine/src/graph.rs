//! The ONNX side of the package contract: which tensors each graph takes and returns.
//!
//! docs/package.md names every input and output and its shape; the manifest fills in the sizes.
//! Checking a freshly loaded session against that turns a mismatched export into one clear error
//! at load time, instead of an ONNX Runtime shape error on the first request.

use std::path::Path;

use ort::session::Session;
use ort::value::{Outlet, TensorElementType, ValueType};

use crate::error::{ShapeDim, format_dims};
use crate::package::{DecoderForm, Manifest};
use crate::{EngineError, Result};

/// Floats per Gaussian in the decoder's output.
pub(crate) const GAUSSIAN_CHANNELS: usize = c4g_scene::CANONICAL_CHANNELS;

/// One named tensor of a graph, its element type and its expected shape.
pub(crate) struct Port {
    pub(crate) name: &'static str,
    pub(crate) element: TensorElementType,
    pub(crate) dims: Vec<ShapeDim>,
}

/// An f32 tensor: every port but the query indices.
fn port(name: &'static str, dims: Vec<ShapeDim>) -> Port {
    Port {
        name,
        element: TensorElementType::Float32,
        dims,
    }
}

/// What one graph of the package must look like.
pub(crate) struct Contract {
    graph: &'static str,
    precision: String,
    inputs: Vec<Port>,
    /// Inputs with a default a run may leave out: initializers of the same name, which ONNX
    /// Runtime lists apart from the inputs (overridable initializers).
    defaults: Vec<Port>,
    outputs: Vec<Port>,
}

/// The ONNX metadata entry in which the export tool (`c4g.package.precision`) stamps the precision a graph
/// computes in; a graph without one computes in f32.
pub(crate) const PRECISION_KEY: &str = "c4g.precision";

use ShapeDim::{Fixed, Free};

impl Contract {
    /// `encoder.onnx`: frames [T, 3, H, W] → features [T, P, C].
    pub(crate) fn encoder(m: &Manifest) -> Self {
        let (h, w) = (m.input.height as usize, m.input.width as usize);
        Self {
            graph: "encoder",
            precision: m.precision.clone(),
            inputs: vec![port(
                "frames",
                vec![Free("T"), Fixed(3), Fixed(h), Fixed(w)],
            )],
            defaults: vec![],
            outputs: vec![features(m)],
        }
    }

    /// `context_projection.onnx` (the precomputed decoder form): features [T, P, C] →
    /// context_projection [T, P, 3C].
    pub(crate) fn context_projection(m: &Manifest) -> Self {
        Self {
            graph: "context_projection",
            precision: m.precision.clone(),
            inputs: vec![features(m)],
            defaults: vec![],
            outputs: vec![context_projection(m)],
        }
    }

    /// `decoder.onnx`: features (and, in the precomputed form, context_projection [T, P, 3C]),
    /// context_times [B, T], target_times [B] → gaussians [B, N, 14]; with a query subset, also
    /// query_indices int64 [Q] → gaussians [B, Q, 14].
    pub(crate) fn decoder(m: &Manifest) -> Self {
        let mut inputs = decoder_inputs(m);
        if m.decoder_form == DecoderForm::Precomputed {
            inputs.push(context_projection(m));
        }
        // query_indices defaults to every query: a full decode leaves it out, and runs exactly as a
        // decoder without it.
        let (queries, defaults) = if m.decoder_query_subset {
            let indices = Port {
                name: "query_indices",
                element: TensorElementType::Int64,
                dims: vec![Free("Q")],
            };
            (Free("Q"), vec![indices])
        } else {
            (Fixed(m.gaussian_count), vec![])
        };
        Self {
            graph: "decoder",
            precision: m.precision.clone(),
            inputs,
            defaults,
            outputs: vec![port(
                "gaussians",
                vec![Free("B"), queries, Fixed(GAUSSIAN_CHANNELS)],
            )],
        }
    }

    /// `feature_decoder.onnx`: the decoder's inputs plus context_feature_maps [T, P, F] →
    /// gaussian_features [B, N, F].
    pub(crate) fn feature_decoder(m: &Manifest, width: usize) -> Self {
        let mut inputs = decoder_inputs(m);
        inputs.push(port(
            "context_feature_maps",
            vec![Free("T"), Fixed(m.tokens_per_frame), Fixed(width)],
        ));
        Self {
            graph: "feature_decoder",
            precision: m.precision.clone(),
            inputs,
            defaults: vec![],
            outputs: vec![port(
                "gaussian_features",
                vec![Free("B"), Fixed(m.gaussian_count), Fixed(width)],
            )],
        }
    }

    /// Checks a loaded session's declared inputs and outputs against the contract.
    pub(crate) fn check(&self, session: &Session, dir: &Path) -> Result<()> {
        let invalid = |reason: String| EngineError::InvalidPackage {
            dir: dir.to_path_buf(),
            reason: format!("{}.onnx: {reason}", self.graph),
        };
        for outlet in session.inputs() {
            if !self.inputs.iter().any(|p| p.name == outlet.name()) {
                return Err(invalid(format!(
                    "unexpected input {:?} (the contract's inputs are {:?})",
                    outlet.name(),
                    self.inputs.iter().map(|p| p.name).collect::<Vec<_>>()
                )));
            }
        }
        for (role, ports, outlets) in [
            ("input", &self.inputs, session.inputs()),
            ("output", &self.outputs, session.outputs()),
        ] {
            for p in ports {
                let outlet = outlets.iter().find(|o| o.name() == p.name).ok_or_else(|| {
                    invalid(format!(
                        "no {role} named {:?} (it has {:?})",
                        p.name,
                        outlets.iter().map(Outlet::name).collect::<Vec<_>>()
                    ))
                })?;
                check_value(p, outlet.dtype())
                    .map_err(|reason| invalid(format!("{role} {reason}")))?;
            }
        }
        let overridable = session.overridable_initializers();
        for p in &self.defaults {
            let found = overridable.iter().find(|o| o.name() == p.name).ok_or_else(|| {
                invalid(format!(
                    "no input {:?} with a default (an initializer of that name); model.json                      declares decoder_query_subset",
                    p.name
                ))
            })?;
            check_value(p, found.dtype()).map_err(|reason| invalid(format!("input {reason}")))?;
        }
        let stamped = session
            .metadata()
            .ok()
            .and_then(|m| m.custom(PRECISION_KEY))
            .unwrap_or_else(|| "f32".to_owned());
        if stamped != self.precision {
            return Err(invalid(format!(
                "the graph computes in {stamped} (its {PRECISION_KEY:?} metadata) but model.json \
                 declares precision {:?}: convert the package again with `python -m c4g.package.precision`",
                self.precision
            )));
        }
        Ok(())
    }
}

fn features(m: &Manifest) -> Port {
    port(
        "features",
        vec![Free("T"), Fixed(m.tokens_per_frame), Fixed(m.feature_width)],
    )
}

/// Floats per token of the context projection: the first decoder layer's q, k and v, each as wide
/// as the features (C4G's decoder has heads × head width = C).
pub(crate) fn context_projection_width(m: &Manifest) -> usize {
    3 * m.feature_width
}

fn context_projection(m: &Manifest) -> Port {
    port(
        "context_projection",
        vec![
            Free("T"),
            Fixed(m.tokens_per_frame),
            Fixed(context_projection_width(m)),
        ],
    )
}

fn decoder_inputs(m: &Manifest) -> Vec<Port> {
    vec![
        features(m),
        port("context_times", vec![Free("B"), Free("T")]),
        port("target_times", vec![Free("B")]),
    ]
}

/// Why a value of type `dtype` does not fit `port`, if it does not. Dynamic dimensions (-1) fit
/// anything; a default's fixed size fits a free dimension.
fn check_value(port: &Port, dtype: &ValueType) -> std::result::Result<(), String> {
    if dtype.tensor_type() != Some(port.element) {
        return Err(format!(
            "{:?} must be a {} tensor, is {dtype}",
            port.name, port.element
        ));
    }
    let Some(shape) = dtype.tensor_shape() else {
        return Err(format!("{:?} must be a tensor", port.name));
    };
    let fits = shape.len() == port.dims.len()
        && shape.iter().zip(&port.dims).all(|(&d, want)| match want {
            Fixed(n) => d < 0 || usize::try_from(d) == Ok(*n),
            Free(_) => true,
        });
    if fits {
        Ok(())
    } else {
        Err(format!(
            "{:?} has shape {:?}, the package declares {}",
            port.name,
            &**shape,
            format_dims(&port.dims)
        ))
    }
}
