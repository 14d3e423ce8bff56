"""Bit operations for compiled kernels, each one or a few machine instructions.

numba gives a kernel no access to the instructions that turn a vector comparison into a
bit mask (``vpmovmskb``, AVX-512's mask registers) or count a word's bits: a loop that
builds a mask from comparisons compiles to a compare and a shift per element. These are
LLVM intrinsics and vector operations written directly, so LLVM picks the instructions
of the machine it compiles for (the vector width, the mask registers where there are
some) and the kernels stay portable.

- :func:`trailing_zeros`: the index of a word's lowest set bit (``llvm.cttz``).
- :func:`bit_count`: the number of set bits (``llvm.ctpop``).
- :func:`word_changes`: which of 64 consecutive 16-bit words of two arrays differ from
  the word after them, as one 64-bit mask (two vector loads of each array, compared).
"""

from __future__ import annotations

from typing import Any

from llvmlite import ir
from numba import types
from numba.core import cgutils
from numba.extending import intrinsic

__all__ = ["CHANGE_SPAN", "bit_count", "trailing_zeros", "word_changes"]

CHANGE_SPAN = 64
"""Words one :func:`word_changes` mask covers (it reads one more)."""

_I64 = ir.IntType(64)


def _unary_count(name: str) -> Any:
    """An intrinsic returning ``llvm.<name>.i64`` of a uint64 (cast from any integer)."""

    def typer(typingctx: Any, value: Any) -> Any:  # pragma: no cover - compiled
        if not isinstance(value, types.Integer):
            return None

        def codegen(context: Any, builder: Any, sig: Any, args: Any) -> Any:
            word = context.cast(builder, args[0], sig.args[0], types.uint64)
            operands = [word]
            arguments = [_I64]
            if name == "cttz":  # defined for zero: 64
                operands.append(ir.Constant(ir.IntType(1), 0))
                arguments.append(ir.IntType(1))
            function = cgutils.get_or_insert_function(
                builder.module, ir.FunctionType(_I64, arguments), f"llvm.{name}.i64"
            )
            return builder.call(function, operands)

        return types.uint64(value), codegen

    typer.__name__ = typer.__qualname__ = f"_{name}"  # the intrinsic's name in numba's registry
    return intrinsic(typer)


trailing_zeros: Any = _unary_count("cttz")
"""``trailing_zeros(word)`` in a compiled kernel: the number of zero bits below the lowest
set bit of a 64-bit word, 64 for zero (a uint64)."""

bit_count: Any = _unary_count("ctpop")
"""``bit_count(word)`` in a compiled kernel: the number of set bits of a 64-bit word (a
uint64)."""


def _words(array: Any) -> bool:
    """Whether a numba type is a C-contiguous 1-D uint16 array (writable or not)."""
    return (
        isinstance(array, types.Array)
        and array.ndim == 1
        and array.dtype == types.uint16
        and array.layout == "C"
    )


def _word_changes(typingctx: Any, first: Any, second: Any, at: Any) -> Any:  # pragma: no cover
    if not (_words(first) and _words(second) and isinstance(at, types.Integer)):
        return None
    signature = types.uint64(first, second, at)

    def codegen(context: Any, builder: Any, sig: Any, args: Any) -> Any:
        vector = ir.VectorType(ir.IntType(16), CHANGE_SPAN).as_pointer()
        offset = context.cast(builder, args[2], sig.args[2], types.intp)
        after = builder.add(offset, ir.Constant(offset.type, 1))
        changed = None
        for array_type, array in zip(sig.args[:2], args[:2], strict=True):
            data = context.make_array(array_type)(context, builder, array).data
            words = builder.load(builder.bitcast(builder.gep(data, [offset]), vector), align=1)
            following = builder.load(builder.bitcast(builder.gep(data, [after]), vector), align=1)
            differs = builder.icmp_unsigned("!=", words, following)
            changed = differs if changed is None else builder.or_(changed, differs)
        return builder.bitcast(changed, _I64)

    return signature, codegen


word_changes: Any = intrinsic(_word_changes)
"""``word_changes(first, second, at)`` in a compiled kernel, for two C-contiguous uint16
arrays: a uint64 whose bit ``j`` is set when ``first[at + j] != first[at + j + 1]`` or
``second[at + j] != second[at + j + 1]``, for ``j`` in ``0 .. 63``. Unchecked: the caller
makes sure ``at + 64`` lies within both arrays."""
