"""Decoding a subset of the queries: the decoder run on some of its N query tokens only.

Query i is Gaussian i. Dropping a query removes its token from the decoder's sequence, so the
Gaussians of the kept queries come out of a shorter attention: they are *not* the full decode's
Gaussians with rows removed (queries attend to each other), only close to them where the dropped
queries drew little attention. That is the approximation the service offers as `drop_queries`
(docs/tradeoffs.md measures it); with every index kept, in order, the result is the full decode.

`query_indices` is int64 [Q] (each in [0, N), no repeats; order is the output's order). The mirror
takes it in both decoder forms, and the export tool writes it as the decoder graph's `query_indices`
input (a Gather on the query tokens, or on the precomputed form's query constants, and on the
anchors), which a package declares with `"decoder_query_subset": true` (docs/package.md).
"""

from __future__ import annotations

import torch
from torch import nn

from .decoder import activate, to_canonical
from .network import C4G
from .precomputed import PrecomputedDecoder


def decode_raw_subset(model: C4G, features: torch.Tensor, context_times: torch.Tensor, target_times: torch.Tensor, query_indices: torch.Tensor) -> torch.Tensor:
    """Raw head output [B, Q, 14] of the queries `query_indices`, as `C4G.decode_raw` for all of them
    (the last layer on the query rows only)."""
    n = model.cfg.queries
    x = model.time_conditioned_tokens(features, context_times, target_times)
    x = torch.cat((x[:, :-n], x[:, -n:][:, query_indices]), dim=1)
    # Traced from the input's shape, so the exported graph slices as many rows as it is given.
    kept = query_indices.shape[0]
    x = model.gmae_decoder(x, query_rows=kept)
    return model.gmae_to_gaussians(x[:, -kept:])


def anchors(model: C4G, query_indices: torch.Tensor, dtype: torch.dtype) -> torch.Tensor:
    """The kept queries' anchor positions [Q, 3]."""
    return model.anchor_positions[query_indices].to(dtype)


def decode_canonical_subset(model: C4G, features, context_times, target_times, query_indices) -> torch.Tensor:
    """Gaussians [B, Q, 14] in the service's canonical layout, as `C4G.decode_canonical`."""
    raw = decode_raw_subset(model, features, context_times, target_times, query_indices)
    return to_canonical(activate(raw, anchors(model, query_indices, raw.dtype)))


def decode_canonical_subset_precomputed(
    decoder: PrecomputedDecoder, features, context_projection, context_times, target_times, query_indices
) -> torch.Tensor:
    """The precomputed form's Gaussians [B, Q, 14] of the queries `query_indices`."""
    raw = decoder.decode_raw(features, context_projection, context_times, target_times, query_indices=query_indices)
    return to_canonical(activate(raw, anchors(decoder.model, query_indices, raw.dtype)))


class SubsetDecoderGraph(nn.Module):
    """decoder.onnx in the plain form with a query subset: features + times + query_indices → gaussians."""

    def __init__(self, model: C4G):
        super().__init__()
        self.model = model

    def forward(self, features, context_times, target_times, query_indices) -> torch.Tensor:
        return decode_canonical_subset(self.model, features, context_times, target_times, query_indices)


class SubsetPrecomputedDecoderGraph(nn.Module):
    """decoder.onnx in the precomputed form with a query subset."""

    def __init__(self, model: C4G):
        super().__init__()
        self.decoder = PrecomputedDecoder(model)

    def forward(self, features, context_projection, context_times, target_times, query_indices) -> torch.Tensor:
        return decode_canonical_subset_precomputed(self.decoder, features, context_projection, context_times, target_times, query_indices)
