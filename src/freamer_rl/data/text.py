"""Word-level tokenization for language observations (e.g. MiniGrid missions).

Any language modality can use :class:`WordTokenizer`: it turns a string into a fixed-length ``int64`` tensor of word
ids that an embedding layer consumes (id 0 = padding, id 1 = unknown word, vocabulary words 2, 3, ...).
"""

from __future__ import annotations

import logging
import re
from collections.abc import Iterable, Sequence

import torch

logger = logging.getLogger(__name__)

__all__ = ["WordTokenizer", "PAD_ID", "UNK_ID", "PAD_TOKEN", "UNK_TOKEN", "split_words"]

PAD_ID = 0
UNK_ID = 1
PAD_TOKEN = "<pad>"
UNK_TOKEN = "<unk>"

_WORD_RE = re.compile(r"[a-z0-9]+")


def split_words(text: str) -> list[str]:
    """Lower-case ``text`` and split it on every non-alphanumeric character (punctuation is dropped).

    >>> split_words("Get the red key, then GO!")
    ['get', 'the', 'red', 'key', 'then', 'go']
    """
    return _WORD_RE.findall(text.lower())


class WordTokenizer:
    """Fixed-length word-level tokenizer.

    Text is lower-cased and split on non-alphanumeric characters. Id ``0`` is padding, id ``1`` an unknown word and
    ``vocab[i]`` gets id ``i + 2``. :meth:`encode` truncates to / right-pads up to ``max_len``.

    Args:
        vocab: the known words (each one lower-case alphanumeric word; duplicates are an error).
        max_len: number of ids :meth:`encode` returns (>= 1).

    Raises:
        ValueError: on an empty, duplicated or non-alphanumeric vocabulary word, or ``max_len < 1``.

    Example:
        >>> tok = WordTokenizer(["go", "to", "the", "goal"], max_len=6)
        >>> tok.encode("Go to the door").tolist()
        [2, 3, 4, 1, 0, 0]
        >>> tok.decode(tok.encode("go to the goal"))
        'go to the goal'
    """

    def __init__(self, vocab: Sequence[str], max_len: int) -> None:
        if isinstance(vocab, str):
            raise ValueError("vocab: expected a sequence of words, got a single string")
        if int(max_len) != max_len or max_len < 1:
            raise ValueError(f"max_len: expected a positive integer, got {max_len!r}")
        words: list[str] = []
        index: dict[str, int] = {}
        for i, word in enumerate(vocab):
            if not isinstance(word, str) or split_words(word) != [word.lower()]:
                raise ValueError(
                    f"vocab[{i}]: expected one alphanumeric word, got {word!r} "
                    "(the tokenizer lower-cases and splits on non-alphanumerics, so it could never match)"
                )
            word = word.lower()
            if word in index:
                raise ValueError(f"vocab[{i}]: duplicate word {word!r} (first at vocab[{index[word] - 2}])")
            index[word] = len(words) + 2
            words.append(word)
        self._words: tuple[str, ...] = (PAD_TOKEN, UNK_TOKEN, *words)
        self._index = index
        self.max_len = int(max_len)

    # ------------------------------------------------------------------------------------------------------------
    @property
    def vocab_size(self) -> int:
        """Number of distinct ids, padding and unknown included (= ``len(vocab) + 2``)."""
        return len(self._words)

    def __len__(self) -> int:
        return self.vocab_size

    @property
    def words(self) -> tuple[str, ...]:
        """All tokens ordered by id: ``("<pad>", "<unk>", *vocab)``."""
        return self._words

    def word_to_id(self, word: str) -> int:
        """Id of one (already split) word; :data:`UNK_ID` when it is not in the vocabulary."""
        return self._index.get(word.lower(), UNK_ID)

    def ids(self, text: str) -> list[int]:
        """Ids of every word of ``text`` (no truncation, no padding)."""
        get = self._index.get
        return [get(w, UNK_ID) for w in split_words(text)]

    def unknown_words(self, text: str) -> list[str]:
        """Words of ``text`` that are not in the vocabulary (useful to validate a vocabulary)."""
        return [w for w in split_words(text) if w not in self._index]

    def encode(self, text: str) -> torch.Tensor:
        """Encode ``text`` into an ``int64`` tensor of shape ``[max_len]``.

        Words beyond ``max_len`` are dropped (a debug message is logged); shorter texts are right-padded with 0.
        """
        ids = self.ids(text)
        if len(ids) > self.max_len:
            logger.debug("text of %d words truncated to max_len=%d: %r", len(ids), self.max_len, text)
            ids = ids[: self.max_len]
        out = torch.zeros(self.max_len, dtype=torch.int64)
        if ids:
            out[: len(ids)] = torch.tensor(ids, dtype=torch.int64)
        return out

    def encode_batch(self, texts: Iterable[str]) -> torch.Tensor:
        """Encode several texts into an ``int64`` tensor of shape ``[N, max_len]``."""
        rows = [self.encode(t) for t in texts]
        if not rows:
            return torch.zeros(0, self.max_len, dtype=torch.int64)
        return torch.stack(rows)

    def decode(self, ids: torch.Tensor | Sequence[int]) -> str:
        """Turn ids (shape ``[L]``) back into a space-joined string.

        Padding ids are skipped, unknown ids become ``"<unk>"``.

        Raises:
            ValueError: if ``ids`` is not one-dimensional or holds an id outside ``[0, vocab_size)``.
        """
        if isinstance(ids, torch.Tensor):
            if ids.ndim != 1:
                raise ValueError(f"ids: expected a 1-D tensor [L], got shape {tuple(ids.shape)}")
            ids = ids.tolist()
        words = []
        n = len(self._words)
        for i in ids:
            i = int(i)
            if i == PAD_ID:
                continue
            if not 0 <= i < n:
                raise ValueError(f"ids: id {i} is outside the vocabulary [0, {n})")
            words.append(self._words[i])
        return " ".join(words)

    def __repr__(self) -> str:
        return f"{type(self).__name__}(vocab_size={self.vocab_size}, max_len={self.max_len})"
