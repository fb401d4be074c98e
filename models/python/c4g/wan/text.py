"""The refiner's text side: umT5's encoder and tokenizer, as WanVACEPipeline turns a caption into the
prompt embedding the transformer cross-attends to.

What the pipeline does (diffusers `WanVACEPipeline._get_t5_prompt_embeds`), and the Rust worker repeats:
1. clean the caption: `ftfy.fix_text`, HTML-unescape twice, strip, collapse whitespace runs to one space;
2. tokenize with umT5's SentencePiece (Unigram) tokenizer, `</s>` appended, truncated to L tokens (the
   `</s>` kept) and padded with `<pad>` (id 0) to L; attention mask 1 on the real tokens;
3. run the encoder on (ids, mask), keep the hidden states of the real tokens, zero the rest.

The graph (`text_encoder.onnx`) is step 3 before the cut: `input_ids` int64 [1, L] and
`attention_mask` int64 [1, L] → `last_hidden_state` f32 [1, L, D]. The tokenizer is the Hugging Face
`tokenizers` JSON (`tokenizer.json`), which the Rust `tokenizers` crate reads.

The real encoder is umT5-XXL (5.7B parameters, ~23 GB in f32): WAN_VACE.md advises precomputed
embeddings for deployments, so the real export writes it only with `--text-encoder`. The tiny fixture
has a 2-layer umT5 of the same class with random weights and a small Unigram tokenizer counted here
from `TINY_CORPUS`, with umT5's normaliser, pre-tokenizer and post-processor layout.
"""

from __future__ import annotations

import math
import unicodedata
from collections import Counter
from pathlib import Path

import torch
from torch import nn

# google/umt5-xxl's encoder as Wan2.1 ships it (text_encoder/config.json of the diffusers checkout).
UMT5_XXL: dict = {
    "vocab_size": 256384,
    "d_model": 4096,
    "d_kv": 64,
    "d_ff": 10240,
    "num_layers": 24,
    "num_heads": 64,
    "relative_attention_num_buckets": 32,
    "relative_attention_max_distance": 128,
    "feed_forward_proj": "gated-gelu",
    "layer_norm_epsilon": 1e-6,
    "dropout_rate": 0.0,
    "tie_word_embeddings": False,
}

# d_model = the tiny transformer's text_dim (32); 2 layers, 2 heads; each layer has its own relative
# position bias (umT5's difference from T5); max distance small enough that 16 tokens reach the far buckets.
UMT5_TINY: dict = {
    **UMT5_XXL,
    "vocab_size": 256,
    "d_model": 32,
    "d_kv": 16,
    "d_ff": 64,
    "num_layers": 2,
    "num_heads": 2,
    "relative_attention_num_buckets": 8,
    "relative_attention_max_distance": 16,
}

TINY_VOCAB = 256  # the tokenizer's pieces, and the tiny encoder's embedding rows
SPECIAL = ["<pad>", "</s>", "<unk>"]  # ids 0, 1, 2, as in umT5

# Captions in the style a vision-language model writes for C4G's scenes (the tiny tokenizer's corpus).
TINY_CORPUS = [
    "A red cube slides across a wooden table while the camera slowly orbits the scene.",
    "Two spheres roll over a checkered floor; the camera stays still.",
    "A person walks through a narrow street lined with parked cars and tall buildings.",
    "The camera pans left over a quiet bedroom with a bed, a lamp and a window.",
    "A dog runs across a green lawn toward a fence, chasing a ball.",
    "Blue and yellow blocks rotate in place in front of a striped wall.",
    "A cyclist rides past a row of trees on a sunny afternoon.",
    "The camera dollies forward into a kitchen where steam rises from a pot.",
    "A small boat drifts on calm water under a cloudy sky.",
    "Leaves fall slowly from a tree as the wind moves its branches.",
    "A child throws a frisbee in a park; people sit on benches nearby.",
    "A car turns at an intersection, its headlights reflecting on the wet road.",
    "Rigid objects move along smooth paths above a textured ground plane.",
    "A deforming orange shape stretches and shrinks next to a grey box.",
    "The scene shows an empty hallway with doors on both sides and soft light.",
    "A cat jumps from a chair onto a desk covered with papers and books.",
    "Waves break on a sandy beach while birds fly over the shore.",
    "A train passes a station platform where passengers are waiting.",
    "Smoke drifts upward from a chimney on a snowy roof.",
    "A hand picks up a cup of coffee from a saucer and lifts it.",
    "The camera moves slowly around a statue in the middle of a square.",
    "A basketball bounces on an outdoor court at dusk.",
    "Clouds move quickly across the sky above green hills.",
    "A dancer spins on a stage under a bright spotlight.",
    "High quality, realistic, sharp details, natural colours, stable camera motion.",
    "Blurry, low quality, distorted, overexposed, static, jpeg artifacts, extra limbs.",
]


def tiny_tokenizer():
    """A Unigram tokenizer laid out like umT5's (`tokenizers` objects): NFKC + umT5's whitespace
    handling, Metaspace pre-tokenizer, `$A </s>` post-processor, `<pad>`/`</s>`/`<unk>` at ids 0/1/2.

    The vocabulary is counted, not trained (the `tokenizers` trainer orders its rare pieces
    differently from run to run): every character of `TINY_CORPUS`'s words (each word with
    umT5's leading "▁") and the substrings of 2-6 characters that cover the most text, each scored
    log(count / total) as a unigram language model scores its pieces."""
    from tokenizers import Regex, Tokenizer, decoders, models, normalizers, pre_tokenizers, processors

    counts: Counter[str] = Counter()
    for line in TINY_CORPUS:
        for word in unicodedata.normalize("NFKC", line).split():
            piece = "▁" + word
            for i in range(len(piece)):
                for j in range(i + 1, min(len(piece), i + 6) + 1):
                    counts[piece[i:j]] += 1
    chars = sorted(p for p in counts if len(p) == 1)
    longer = sorted((p for p in counts if len(p) > 1 and counts[p] > 1), key=lambda p: (-counts[p] * len(p), p))
    pieces = chars + longer[: TINY_VOCAB - len(SPECIAL) - len(chars)]
    total = sum(counts[p] for p in pieces)
    scored = sorted(((p, round(math.log(counts[p] / total), 6)) for p in pieces), key=lambda e: (-e[1], e[0]))
    vocab = [(token, 0.0) for token in SPECIAL] + scored

    tok = Tokenizer(models.Unigram(vocab, unk_id=SPECIAL.index("<unk>"), byte_fallback=False))
    tok.normalizer = normalizers.Sequence([normalizers.NFKC(), normalizers.Strip(left=False, right=True), normalizers.Replace(Regex(" {2,}"), "▁")])
    tok.pre_tokenizer = pre_tokenizers.Metaspace(replacement="▁", prepend_scheme="always")
    tok.decoder = decoders.Metaspace(replacement="▁", prepend_scheme="always")
    tok.add_special_tokens(SPECIAL)
    eos = tok.token_to_id("</s>")
    tok.post_processor = processors.TemplateProcessing(single="$A </s>", pair="$A </s> $B </s>", special_tokens=[("</s>", eos)])
    return tok


def fast_tokenizer(tokenizer_json: Path):
    """The transformers tokenizer WanVACEPipeline takes, over a `tokenizer.json`."""
    from transformers import T5TokenizerFast

    return T5TokenizerFast(tokenizer_file=str(tokenizer_json), eos_token="</s>", unk_token="<unk>", pad_token="<pad>", extra_ids=0)


def build_text_encoder(cfg: dict, seed: int | None = None):
    """A transformers `UMT5EncoderModel` from `cfg`, with deterministic random weights under `seed`
    (norm scales perturbed too, as for the transformer, so every weight matters)."""
    from transformers import UMT5Config, UMT5EncoderModel

    from .configs import randomise

    if seed is not None:
        torch.manual_seed(seed)
    model = UMT5EncoderModel(UMT5Config(**cfg, is_encoder_decoder=False, use_cache=False))
    if seed is not None:
        randomise(model, seed + 1)
    return model.eval()


class TextEncoderGraph(nn.Module):
    """(input_ids, attention_mask) → last_hidden_state, as the pipeline calls the encoder."""

    def __init__(self, encoder: nn.Module):
        super().__init__()
        self.encoder = encoder

    def forward(self, input_ids, attention_mask):
        return self.encoder(input_ids=input_ids, attention_mask=attention_mask).last_hidden_state


def export_text_encoder(encoder: nn.Module, tokens: int, path: Path, compact: bool = False, external_data: bool | None = None) -> None:
    """The encoder graph at `tokens` tokens (weights keep their transformers names without `encoder.`)."""
    from .onnx_graphs import export_graph

    device = next(encoder.parameters()).device
    ids = torch.zeros(1, tokens, dtype=torch.int64, device=device)
    ids[0, :3] = torch.tensor([5, 6, 1])
    mask = (ids != 0).long()
    mask[0, 2] = 1
    export_graph(
        TextEncoderGraph(encoder),
        (ids, mask),
        path,
        ["input_ids", "attention_mask"],
        ["last_hidden_state"],
        strip_prefix="encoder.",
        keep_names=True,
        external_data=external_data,
        compact=compact,
    )


def graph_signature(tokens: int, dim: int) -> dict:
    return {"inputs": {"input_ids": [1, tokens], "attention_mask": [1, tokens]}, "outputs": {"last_hidden_state": [1, tokens, dim]}}


def manifest_entry(tokens: int) -> dict:
    """refiner.json's `text.encoder`: how a caption becomes the embedding (what the worker repeats)."""
    return {
        "clean": "ftfy.fix_text, html.unescape twice, strip, whitespace runs -> one space (diffusers' prompt_clean)",
        "tokenize": f"tokenizer.json with its post-processor ('$A </s>'), truncated to {tokens}, padded with id 0",
        "mask": "1 on the real tokens (those before padding)",
        "embedding": "last_hidden_state of the real tokens, zeros after",
        "input_dtype": "int64",
        "negative_prompt": "'' (empty) unless the job gives one",
    }
