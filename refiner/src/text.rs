//! Captions to prompt embeddings, as diffusers' WanVACEPipeline makes them from a prompt:
//! 1. [`clean_caption`]: the text repairs of ftfy's `fix_text`, HTML entities decoded twice more,
//!    whitespace runs collapsed to one space and the ends trimmed (diffusers' `prompt_clean`);
//! 2. umT5's tokenizer (`tokenizer.json`, with its `</s>`), truncated to the package's `L` tokens
//!    with the `</s>` kept, padded with `<pad>`; attention mask 1 on the real tokens;
//! 3. the encoder graph, whose hidden states are kept for the real tokens and zeroed after them.
//!
//! The reference outputs in the tiny fixture (`reference/text.json`, `text.npz`) come from the
//! pipeline's own `encode_prompt`; `tests/text_reference.rs` holds this module to them.

use std::path::Path;
use std::sync::OnceLock;

use c4g_runtime::{Graph, RuntimeError, SessionOptions, create_session};
use ort::value::TensorRef;
use tokenizers::{Tokenizer, TruncationParams};
use unicode_normalization::UnicodeNormalization;

use crate::{RefinerError, Result};

/// The graph's inputs and output (see `models/python/c4g/wan/text.py`).
const INPUT_IDS: &str = "input_ids";
const ATTENTION_MASK: &str = "attention_mask";
const HIDDEN_STATE: &str = "last_hidden_state";
/// umT5's padding token.
const PAD_TOKEN: &str = "<pad>";

/// A caption's tokens, padded to the package's length.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Tokens {
    /// Token ids, `L` of them: the caption's, `</s>`, then `<pad>`.
    pub ids: Vec<i64>,
    /// 1 on the real tokens (`</s>` included), 0 on the padding.
    pub mask: Vec<i64>,
    /// How many tokens are real.
    pub len: usize,
}

/// umT5's tokenizer and encoder graph of a package.
pub struct TextEncoder {
    tokenizer: Tokenizer,
    pad_id: i64,
    graph: Graph,
    /// The empty prompt's embedding, once computed: every job without a negative prompt needs it.
    empty: OnceLock<Vec<f32>>,
    tokens: usize,
    dim: usize,
}

impl std::fmt::Debug for TextEncoder {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("TextEncoder")
            .field("tokens", &self.tokens)
            .field("dim", &self.dim)
            .finish_non_exhaustive()
    }
}

impl TextEncoder {
    /// Loads `tokenizer` (a Hugging Face `tokenizer.json`) and the encoder `graph`, for
    /// embeddings of `tokens` × `dim`.
    pub(crate) fn load(
        tokenizer: &Path,
        graph: &Path,
        tokens: usize,
        dim: usize,
        options: &SessionOptions,
    ) -> Result<Self> {
        let invalid = |reason: String| RefinerError::InvalidPackage {
            dir: tokenizer.parent().unwrap_or(tokenizer).to_path_buf(),
            reason,
        };
        let mut tokenizer_model = Tokenizer::from_file(tokenizer)
            .map_err(|e| invalid(format!("{} is unreadable: {e}", tokenizer.display())))?;
        tokenizer_model
            .with_truncation(Some(TruncationParams {
                max_length: tokens,
                ..TruncationParams::default()
            }))
            .map_err(|e| invalid(format!("the tokenizer cannot truncate to {tokens}: {e}")))?;
        let pad_id = tokenizer_model
            .token_to_id(PAD_TOKEN)
            .ok_or_else(|| invalid(format!("the tokenizer has no {PAD_TOKEN} token")))?;
        Ok(Self {
            tokenizer: tokenizer_model,
            pad_id: i64::from(pad_id),
            graph: Graph::new("text encoder", create_session(graph, options)?),
            empty: OnceLock::new(),
            tokens,
            dim,
        })
    }

    /// The cleaned caption's tokens, truncated and padded to `L`.
    pub fn tokenize(&self, caption: &str) -> Result<Tokens> {
        let clean = clean_caption(caption);
        let encoding = self.tokenizer.encode(clean, true).map_err(|e| {
            RefinerError::InvalidRequest(format!("the caption cannot be tokenized: {e}"))
        })?;
        let mut ids: Vec<i64> = encoding.get_ids().iter().map(|&id| i64::from(id)).collect();
        let len = ids.len().min(self.tokens);
        ids.truncate(len);
        ids.resize(self.tokens, self.pad_id);
        let mut mask = vec![1; len];
        mask.resize(self.tokens, 0);
        Ok(Tokens { ids, mask, len })
    }

    /// The caption's prompt embedding, `[L, D]`: the encoder's hidden states of the real tokens,
    /// zeros after them.
    pub fn embed(&self, caption: &str) -> Result<Vec<f32>> {
        let empty = clean_caption(caption).is_empty();
        if empty && let Some(embedding) = self.empty.get() {
            return Ok(embedding.clone());
        }
        let embedding = self.run_encoder(caption)?;
        if empty {
            let _ = self.empty.set(embedding.clone());
        }
        Ok(embedding)
    }

    fn run_encoder(&self, caption: &str) -> Result<Vec<f32>> {
        let tokens = self.tokenize(caption)?;
        let shape = vec![1, self.tokens];
        let ids = TensorRef::from_array_view((shape.clone(), &tokens.ids[..]))
            .map_err(RuntimeError::ort("preparing the token ids"))?;
        let mask = TensorRef::from_array_view((shape, &tokens.mask[..]))
            .map_err(RuntimeError::ort("preparing the attention mask"))?;
        let expected = [1, self.tokens, self.dim];
        let mut embedding = self.graph.run(
            ort::inputs![INPUT_IDS => ids, ATTENTION_MASK => mask],
            |outputs| Ok(outputs.f32(HIDDEN_STATE, &expected)?.to_vec()),
        )?;
        embedding[tokens.len * self.dim..].fill(0.0);
        Ok(embedding)
    }
}

/// A caption as the reference pipeline hands it to the tokenizer.
///
/// First the repairs of ftfy's `fix_text` (default settings), line by line and repeated until
/// nothing changes: HTML entities decoded (not on a line holding a literal `<`, which may be
/// markup), Latin ligatures and full-width forms to plain letters, curly quotes to straight ones,
/// line separators to `\n`, terminal colour codes and stray control characters removed, NFC.
/// Then HTML entities decoded twice, whitespace runs to one space, the ends trimmed.
///
/// Not repaired: mojibake (text decoded with the wrong codec, e.g. "cafÃ©"), which ftfy detects
/// and re-decodes; a caption holding it tokenizes differently here than in the reference.
pub fn clean_caption(caption: &str) -> String {
    // ftfy stops decoding entities at the first line holding a '<', for the rest of the text.
    let mut unescape = true;
    let fixed: String = caption
        .split_inclusive('\n')
        .map(|line| {
            unescape &= !line.contains('<');
            fix_line(line, unescape)
        })
        .collect();
    let once = html_unescape(&fixed, Entities::Python);
    let twice = html_unescape(&once, Entities::Python);
    collapse_whitespace(&twice)
}

/// ftfy's fixes on one line, to a fixed point.
fn fix_line(line: &str, unescape: bool) -> String {
    let mut text = line.to_owned();
    loop {
        let decoded = if unescape {
            html_unescape(&text, Entities::Ftfy)
        } else {
            text.clone()
        };
        // ftfy's order: the character fixes, then terminal codes, then the other controls (ESC
        // among them), then NFC.
        let plain: String = decoded
            .chars()
            .map(from_c1_control)
            .collect::<String>()
            .replace("\r\n", "\n")
            .chars()
            .flat_map(plain_char)
            .collect();
        let next: String = remove_terminal_escapes(&plain)
            .chars()
            .filter(|&c| !is_stray_control(c))
            .nfc()
            .collect();
        if next == text {
            return text;
        }
        text = next;
    }
}

/// Which character references a pass decodes.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Entities {
    /// Python's `html.unescape`: named references with or without their `;` (the latter only for
    /// the 106 legacy names, longest prefix first), numeric ones with or without it.
    Python,
    /// ftfy's: only references closed by `;`, of at most 24 letters and digits.
    Ftfy,
}

/// The HTML names that are references even without a closing `;` (HTML's legacy entities).
const LEGACY_ENTITIES: [&str; 106] = [
    "AElig", "AMP", "Aacute", "Acirc", "Agrave", "Aring", "Atilde", "Auml", "COPY", "Ccedil",
    "ETH", "Eacute", "Ecirc", "Egrave", "Euml", "GT", "Iacute", "Icirc", "Igrave", "Iuml", "LT",
    "Ntilde", "Oacute", "Ocirc", "Ograve", "Oslash", "Otilde", "Ouml", "QUOT", "REG", "THORN",
    "Uacute", "Ucirc", "Ugrave", "Uuml", "Yacute", "aacute", "acirc", "acute", "aelig", "agrave",
    "amp", "aring", "atilde", "auml", "brvbar", "ccedil", "cedil", "cent", "copy", "curren", "deg",
    "divide", "eacute", "ecirc", "egrave", "eth", "euml", "frac12", "frac14", "frac34", "gt",
    "iacute", "icirc", "iexcl", "igrave", "iquest", "iuml", "laquo", "lt", "macr", "micro",
    "middot", "nbsp", "not", "ntilde", "oacute", "ocirc", "ograve", "ordf", "ordm", "oslash",
    "otilde", "ouml", "para", "plusmn", "pound", "quot", "raquo", "reg", "sect", "shy", "sup1",
    "sup2", "sup3", "szlig", "thorn", "times", "uacute", "ucirc", "ugrave", "uml", "uuml",
    "yacute", "yen", "yuml",
];

/// Decodes HTML character references in `text` as `mode` says.
fn html_unescape(text: &str, mode: Entities) -> String {
    let mut out = String::with_capacity(text.len());
    let mut rest = text;
    while let Some(amp) = rest.find('&') {
        out.push_str(&rest[..amp]);
        let after = &rest[amp + 1..];
        match reference(after, mode) {
            Some((decoded, used)) => {
                out.push_str(&decoded);
                rest = &after[used..];
            }
            None => {
                out.push('&');
                rest = after;
            }
        }
    }
    out.push_str(rest);
    out
}

/// The reference at the start of `s` (just after a `&`): what it decodes to and how many bytes
/// of `s` it spans; `None` when there is none and the `&` stays.
fn reference(s: &str, mode: Entities) -> Option<(String, usize)> {
    let semicolon = |at: usize| s[at..].starts_with(';');
    if let Some(number) = s.strip_prefix('#') {
        let (hex, digits) = match number.strip_prefix(['x', 'X']) {
            Some(h) if h.starts_with(|c: char| c.is_ascii_hexdigit()) => (true, h),
            _ => (false, number),
        };
        let radix = if hex { 16 } else { 10 };
        let len = digits
            .find(|c: char| !c.is_digit(radix))
            .unwrap_or(digits.len());
        let end = s.len() - digits.len() + len;
        let closed = semicolon(end);
        if len == 0 || (mode == Entities::Ftfy && !closed) {
            return None;
        }
        let code = u32::from_str_radix(&digits[..len], radix).unwrap_or(u32::MAX);
        return Some((numeric_reference(code), end + usize::from(closed)));
    }
    let name_len: usize = match mode {
        Entities::Python => s
            .chars()
            .take_while(|c| !matches!(c, '\t' | '\n' | '\u{c}' | ' ' | '<' | '&' | '#' | ';'))
            .take(32)
            .map(char::len_utf8)
            .sum(),
        Entities::Ftfy => s
            .chars()
            .take_while(char::is_ascii_alphanumeric)
            .take(24)
            .map(char::len_utf8)
            .sum(),
    };
    if name_len == 0 {
        return None;
    }
    let name = &s[..name_len];
    if semicolon(name_len) {
        let candidate = format!("&{name};");
        let decoded = html_escape::decode_html_entities(&candidate);
        if decoded != candidate {
            return Some((decoded.into_owned(), name_len + 1));
        }
    }
    if mode == Entities::Ftfy {
        return None;
    }
    // The longest legacy name that starts the run, the rest kept as text.
    (1..=name_len)
        .rev()
        .filter(|&n| name.is_char_boundary(n))
        .find(|&n| LEGACY_ENTITIES.contains(&&name[..n]))
        .map(|n| {
            let candidate = format!("&{};", &name[..n]);
            (
                html_escape::decode_html_entities(&candidate).into_owned(),
                n,
            )
        })
}

/// A numeric reference's text, with HTML's substitutions for code points that are not
/// characters: NUL and surrogates become U+FFFD, C1 controls the Windows-1252 character, other
/// controls and non-characters nothing.
fn numeric_reference(code: u32) -> String {
    match code {
        0 => "\u{fffd}".to_owned(),
        0x0d => "\r".to_owned(),
        0x80..=0x9f => from_c1_control(char::from_u32(code).unwrap_or('\u{fffd}')).to_string(),
        0xd800..=0xdfff | 0x11_0000.. => "\u{fffd}".to_owned(),
        0x1..=0x8 | 0xb | 0xe..=0x1f | 0x7f | 0xfdd0..=0xfdef => String::new(),
        c if c & 0xfffe == 0xfffe => String::new(),
        c => char::from_u32(c).map(String::from).unwrap_or_default(),
    }
}

/// A C1 control character (U+0080–U+009F) as the Windows-1252 character of the same byte, as ftfy
/// reads them (text that went through Latin-1 by mistake); the five bytes Windows-1252 leaves
/// undefined stay as they are.
fn from_c1_control(c: char) -> char {
    const WINDOWS_1252: [char; 32] = [
        '€', '\u{81}', '‚', 'ƒ', '„', '…', '†', '‡', 'ˆ', '‰', 'Š', '‹', 'Œ', '\u{8d}', 'Ž',
        '\u{8f}', '\u{90}', '‘', '’', '“', '”', '•', '–', '—', '˜', '™', 'š', '›', 'œ', '\u{9d}',
        'ž', 'Ÿ',
    ];
    match c {
        '\u{80}'..='\u{9f}' => WINDOWS_1252[c as usize - 0x80],
        _ => c,
    }
}

/// A character as ftfy's ligature, width, quote and line-break fixes leave it.
fn plain_char(c: char) -> Vec<char> {
    let replacement = match c {
        // Latin ligatures and digraphs, spelled out.
        'Ĳ' => "IJ",
        'ĳ' => "ij",
        'ŉ' => "ʼn",
        'Ǳ' => "DZ",
        'ǲ' => "Dz",
        'ǳ' => "dz",
        'Ǆ' => "DŽ",
        'ǅ' => "Dž",
        'ǆ' => "dž",
        'Ǉ' => "LJ",
        'ǈ' => "Lj",
        'ǉ' => "lj",
        'Ǌ' => "NJ",
        'ǋ' => "Nj",
        'ǌ' => "nj",
        'ﬀ' => "ff",
        'ﬁ' => "fi",
        'ﬂ' => "fl",
        'ﬃ' => "ffi",
        'ﬄ' => "ffl",
        'ﬅ' => "ſt",
        'ﬆ' => "st",
        // Curly quotes (and the modifier apostrophe) to straight ones.
        '\u{02bc}' | '\u{2018}'..='\u{201b}' => "'",
        '\u{201c}'..='\u{201f}' => "\"",
        // Line and paragraph separators, and a lone carriage return, to a line feed (ftfy's U+0085
        // never gets here: it was read as Windows-1252 first).
        '\r' | '\u{2028}' | '\u{2029}' => "\n",
        // The ideographic space, and full- and half-width forms, to their usual width.
        '\u{3000}' => " ",
        '\u{ff01}'..='\u{ffef}' => return c.nfkc().collect(),
        _ => return vec![c],
    };
    replacement.chars().collect()
}

/// The control characters ftfy drops: C0 controls but tab, line feed, form feed and carriage
/// return; DEL; the deprecated format characters; the byte-order mark; interlinear annotations.
fn is_stray_control(c: char) -> bool {
    matches!(c,
        '\u{0}'..='\u{8}' | '\u{b}' | '\u{e}'..='\u{1f}' | '\u{7f}'
        | '\u{206a}'..='\u{206f}' | '\u{feff}' | '\u{fff9}'..='\u{fffc}')
}

/// Removes ANSI terminal sequences `ESC [ digits-and-semicolons letter`.
fn remove_terminal_escapes(text: &str) -> String {
    let mut out = String::with_capacity(text.len());
    let mut rest = text;
    while let Some(start) = rest.find("\u{1b}[") {
        out.push_str(&rest[..start]);
        let after = &rest[start + 2..];
        let params = after
            .find(|c: char| !(c.is_ascii_digit() || c == ';'))
            .unwrap_or(after.len());
        match after[params..].chars().next() {
            Some(letter) if letter.is_ascii_alphabetic() => {
                rest = &after[params + letter.len_utf8()..];
            }
            _ => {
                out.push('\u{1b}');
                rest = &rest[start + 1..];
            }
        }
    }
    out.push_str(rest);
    out
}

/// Python's `re.sub(r"\s+", " ", text).strip()`: `\s` is Unicode whitespace, which for Python
/// also takes in the information separators U+001C–U+001F.
fn collapse_whitespace(text: &str) -> String {
    let is_space = |c: char| c.is_whitespace() || ('\u{1c}'..='\u{1f}').contains(&c);
    text.split(is_space)
        .filter(|word| !word.is_empty())
        .collect::<Vec<_>>()
        .join(" ")
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn whitespace_runs_become_one_space_and_the_ends_go() {
        assert_eq!(clean_caption("  a\t b\n\nc \u{a0}d  "), "a b c d");
        assert_eq!(clean_caption(""), "");
        assert_eq!(clean_caption(" \n\t "), "");
    }

    #[test]
    fn entities_are_decoded_to_a_fixed_point_except_on_lines_with_markup() {
        assert_eq!(clean_caption("&amp;amp;amp;amp;"), "&");
        // A literal '<' keeps ftfy from decoding that line: only the two later passes run.
        assert_eq!(clean_caption("<b> &amp;amp;amp;"), "<b> &amp;");
        assert_eq!(clean_caption("<b>\n&amp;amp;amp;"), "<b> &amp;");
        assert_eq!(clean_caption("&amp;amp;amp;\n<b>"), "& <b>");
        // Entities without their semicolon, as Python's html.unescape reads them.
        assert_eq!(
            clean_caption("AT&T &copy &copyright &amp &ampx &#39 &#x41;"),
            "AT&T \u{a9} \u{a9}right & &x ' A"
        );
    }

    #[test]
    fn typography_is_plain() {
        assert_eq!(
            clean_caption("\u{201c}hi\u{201d} it\u{2019}s \u{fb01}ne \u{ff21}\u{3000}b"),
            "\"hi\" it's fine A b"
        );
        assert_eq!(clean_caption("cafe\u{301}"), "caf\u{e9}");
        // A lone ESC is not a colour code, but a stray control character all the same.
        assert_eq!(clean_caption("\u{1b}[1;31mred\u{1b}[0m \u{1b}x"), "red x");
        assert_eq!(clean_caption("a\u{0}b\u{7}c\u{feff}d"), "abcd");
        // C1 controls read as Windows-1252: U+0085 is an ellipsis, U+0093 a quote (then uncurled).
        assert_eq!(clean_caption("a\u{85}b \u{93}c"), "a\u{2026}b \"c");
    }
}
