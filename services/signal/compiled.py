"""The one module that imports Numba: :func:`kernel` compiles a hot numeric loop to machine code.

Why: the estimators and the ingest path make thousands of small NumPy calls a scan, and each pays
the interpreter's fixed overhead whatever its size.  A
kernel runs such a loop as one call.  Kernels are ordinary Python functions over NumPy arrays and
scalars; the math stays in the module it belongs to (``corner.model``, ``stream.step_features``…), decorated
with :func:`kernel` — one implementation per idea, this module only holds the compiler's settings.

Settings, and why:
- ``cache=True``: compiled code is kept on disk, so only the first process after an install or an
  edit compiles (``lelsonar warm-up``, which ``make`` runs after
  installing); a later process loads the machine code on a kernel's first call.
- The cache lives in a directory named after a digest of every module holding kernels
  (:data:`KERNEL_MODULES`) and the Numba version: Numba checks only a kernel's own file, so a kernel
  calling another module's kernel would otherwise keep stale machine code after that module changed.
- ``nogil=True``: a kernel releases the GIL, so the live source's threads keep receiving.
- ``error_model="numpy"``: division by zero gives inf/NaN as NumPy does, not an exception.
- no ``fastmath``: results stay IEEE, so a kernel agrees with the equivalent NumPy to rounding.  The one
  exception, :func:`summing_kernel`, is for sums whose every order of addition gives the same number (or whose
  bound holds for any order): it lets LLVM reassociate their additions, which is what lets a sum run in vector
  lanes, and nothing else (NaN, infinities and signed zeros stay IEEE).
- Recursion is avoided: Numba has crashed loading a recursive kernel from its cache.

The compiler-level helpers here: :func:`float32_at`, a float32 view of bytes at any offset (a protobuf field's),
typed unaligned, so that a kernel reads a payload's waveform where it lies instead of copying it;
:func:`prefetch`, a hint to fetch the bytes a kernel reads next while it reads others; :func:`unowned`, an array
handed on without its reference count; :func:`array_at`, an
array handed to a kernel as its address (an integer's conversion where an array's costs a look-up of its type);
and :func:`float32_from_bits`, a float32 bit pattern reinterpreted as its number.  :func:`entry_point` gives a
kernel's machine code for one signature, to call without the dispatcher's per-call type resolution.
"""

from __future__ import annotations

import hashlib
import importlib
import importlib.machinery
import importlib.util
import logging
import os
from collections.abc import Callable
from pathlib import Path
from typing import TypeVar

import numba
from llvmlite import ir
from numba import types
from numba.core import cgutils
from numba.extending import intrinsic
from numba.np.arrayobj import make_array, populate_array

F = TypeVar("F", bound=Callable[..., object])

log = logging.getLogger(__name__)

#: Every module of this package with a :func:`kernel` (a test checks the list is complete).
KERNEL_MODULES = (
    "lelsonar.signal.echo_timing",
    "lelsonar.signal.energy",
    "lelsonar.signal.extrema",
    "lelsonar.signal.summation",
    "lelsonar.reconstruct.estimate.corner.edge",
    "lelsonar.reconstruct.estimate.corner.model",
    "lelsonar.reconstruct.estimate.corner.pitch",
    "lelsonar.reconstruct.estimate.corner.search",
    "lelsonar.reconstruct.estimate.corner.solver",
    "lelsonar.reconstruct.estimate.corner.wall",
    "lelsonar.reconstruct.estimate.correct",
    "lelsonar.reconstruct.estimate.fit",
    "lelsonar.reconstruct.estimate.lel",
    "lelsonar.reconstruct.estimate.normals",
    "lelsonar.reconstruct.estimate.pipeline",
    "lelsonar.reconstruct.estimate.quality",
    "lelsonar.reconstruct.estimate.robust",
    "lelsonar.reconstruct.estimate.split",
    "lelsonar.reconstruct.estimate.surfaces.amplitude_top",
    "lelsonar.reconstruct.estimate.surfaces.piston",
    "lelsonar.reconstruct.estimate.surfaces.regions",
    "lelsonar.reconstruct.estimate.surfaces.slopes",
    "lelsonar.reconstruct.stream.candidates",
    "lelsonar.reconstruct.stream.fastwire",
    "lelsonar.reconstruct.stream.step_features",
)


def _cache_dir() -> Path | None:
    """The directory for this build's machine code, made if need be (a warning then: compiling comes next).

    Next to the sources (``__pycache__``), or under the user's cache directory if that is read-only;
    None (Numba's own default) if neither can be written.
    """
    here = Path(__file__).resolve().parent
    digest = hashlib.blake2b(numba.__version__.encode(), digest_size=8)
    digest.update(Path(__file__).read_bytes())  # (the helpers below are compiled into the kernels that use them)
    for name in KERNEL_MODULES:
        digest.update(module_source(name).read_bytes())
    user_cache = Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache") / "lelsonar"
    for base in (here / "__pycache__", user_cache):
        path = base / f"numba-{digest.hexdigest()}"
        if path.is_dir() and os.access(path, os.W_OK):
            return path
        try:
            path.mkdir(parents=True)
        except OSError:
            continue
        log.warning(
            "first run of this build: compiling the numeric kernels (~40 s on 2 cores, once; "
            "`lelsonar warm-up` does it ahead). Cache: %s",
            path,
        )
        return path
    return None


def module_source(name: str) -> Path:
    """The source file of a module, found without importing it or its own package (whose ``__init__`` may
    import kernels of this list while this module is still loading); the packages above those are imported."""
    package, _, _ = name.rpartition(".")
    outer = importlib.util.find_spec(package) if package else None
    where = None if outer is None else outer.submodule_search_locations
    spec = importlib.machinery.PathFinder.find_spec(name, where) if where is not None else None
    if spec is None or spec.origin is None:
        raise ImportError(f"{name}: no source file; KERNEL_MODULES names a module that does not exist")
    return Path(spec.origin)


_CACHE = _cache_dir()
if _CACHE is not None:
    # Read by each kernel's cache as it is decorated, after this.
    numba.config.CACHE_DIR = str(_CACHE)  # type: ignore[attr-defined]  # numba.config makes its options at import


def cache_dir() -> Path | None:
    """Where this build's machine code is kept (None: Numba's default)."""
    return _CACHE


def kernel(func: F) -> F:
    """Compile ``func`` with the project's Numba settings (see the module docstring)."""
    return numba.njit(cache=True, nogil=True, error_model="numpy")(func)  # type: ignore[return-value]


def summing_kernel(func: F) -> F:
    """:func:`kernel` for a loop of sums that give the same result in any order of addition — an exact sum, or one
    checked against a bound that holds for every order: its additions may be reassociated (several partial sums
    side by side, in vector lanes).  Nothing else of ``fastmath``: a NaN or an infinity propagates as in IEEE."""
    return numba.njit(cache=True, nogil=True, error_model="numpy", fastmath={"reassoc"})(func)  # type: ignore[return-value]


def entry_point(func: F, *examples: object) -> F:
    """``func``'s machine code for arguments of the types of ``examples``, called without its dispatcher (compiled,
    or loaded from the cache, if need be): the dispatcher resolves every argument's type on every call, a fixed
    cost that a kernel called once a sample pays a sample.  The caller passes arguments of exactly those types
    every time (nothing checks them; an object of the wrong kind is refused, a number converted); ``func`` itself
    if it is not a kernel (a test's stand-in)."""
    if not isinstance(func, numba.core.registry.CPUDispatcher):
        return func
    return func.compile(tuple(numba.typeof(x) for x in examples))  # type: ignore[return-value]


def kernels() -> dict[str, numba.core.registry.CPUDispatcher]:
    """Every kernel of :data:`KERNEL_MODULES`, by qualified name (imports those modules)."""
    found = {}
    for module_name in KERNEL_MODULES:
        module = importlib.import_module(module_name)
        found.update(
            {
                f"{module_name}.{name}": obj
                for name, obj in vars(module).items()
                if isinstance(obj, numba.core.registry.CPUDispatcher) and obj.py_func.__module__ == module_name
            }
        )
    return found


@intrinsic
def float32_at(typingctx, buf, start, count):
    """A read-only float32 view of ``count`` values at byte ``start`` of the 1-d uint8 array ``buf``, typed
    unaligned: its loads make no assumption on the address, which a protobuf field's bytes lie at any of (a view
    by ``.view`` would be typed aligned, and reading it at such an address undefined).

    The view does not keep ``buf`` alive (no reference counted, as :func:`array_at`): a view that holds one pays
    an atomic increment and decrement each time the kernel copies it, which a pass over a sample's waveforms
    does dozens of times.  So the view is used only inside the kernel call that holds ``buf`` (an argument, or
    an array made from one) and is never returned from it.

    The caller bounds ``start`` and ``count`` (``start + 4·count ≤ buf.size``): nothing is checked here."""
    if not (isinstance(buf, types.Array) and buf.ndim == 1 and buf.dtype == types.uint8):
        return None
    if not (isinstance(start, types.Integer) and isinstance(count, types.Integer)):
        return None
    view = types.Array(types.float32, 1, "C", readonly=True, aligned=False)

    def codegen(context, builder, sig, args):
        source = make_array(sig.args[0])(context, builder, value=args[0])
        first = context.cast(builder, args[1], sig.args[1], types.intp)
        n = context.cast(builder, args[2], sig.args[2], types.intp)
        out = make_array(sig.return_type)(context, builder)
        itemsize = context.get_constant(types.intp, 4)
        populate_array(
            out,
            data=builder.bitcast(builder.gep(source.data, [first]), out.data.type),
            shape=cgutils.pack_array(builder, [n]),
            strides=cgutils.pack_array(builder, [itemsize]),
            itemsize=itemsize,
            meminfo=None,
        )
        return out._getvalue()

    return view(buf, start, count), codegen


@intrinsic
def prefetch(typingctx, buf, at):
    """Ask the processor to bring the cache line of byte ``at`` of the 1-d uint8 array ``buf`` closer (LLVM's
    ``llvm.prefetch``, a read): a hint, which changes no value and never faults, so that loads whose addresses
    depend on one another (a protobuf walk from one field's length to the next field) wait for memory once,
    not once each.  Nothing is checked: an address outside ``buf`` is only a useless hint."""
    if not (isinstance(buf, types.Array) and buf.ndim == 1 and buf.dtype == types.uint8):
        return None
    if not isinstance(at, types.Integer):
        return None

    def codegen(context, builder, sig, args):
        source = make_array(sig.args[0])(context, builder, value=args[0])
        index = context.cast(builder, args[1], sig.args[1], types.intp)
        address = builder.bitcast(builder.gep(source.data, [index]), ir.IntType(8).as_pointer())
        i32 = ir.IntType(32)
        hint = cgutils.get_or_insert_function(
            builder.module, ir.FunctionType(ir.VoidType(), [address.type, i32, i32, i32]), "llvm.prefetch.p0i8"
        )
        builder.call(hint, [address, i32(0), i32(3), i32(1)])  # a read, kept in every cache level, of data
        return context.get_dummy_value()

    return types.none(buf, at), codegen


@intrinsic
def unowned(typingctx, array):
    """``array`` itself (its data, shape and strides), not keeping its memory alive: as :func:`float32_at`, for an
    array a kernel hands on many times (a payload's bytes, to the functions that read it), used only while the
    kernel holds the array it came from, and never returned.  A counted array pays an atomic increment and
    decrement each time it is handed on; this one pays nothing."""
    if not isinstance(array, types.Array):
        return None

    def codegen(context, builder, sig, args):
        source = make_array(sig.args[0])(context, builder, value=args[0])
        out = make_array(sig.return_type)(context, builder)
        populate_array(
            out,
            data=source.data,
            shape=source.shape,
            strides=source.strides,
            itemsize=source.itemsize,
            meminfo=None,
        )
        return out._getvalue()

    return array(array), codegen


@intrinsic
def array_at(typingctx, address, shape, dtype):
    """A C-contiguous array of ``shape`` (an int, or a tuple of ints) and ``dtype`` (a NumPy scalar type, e.g.
    ``np.float64``) over the memory at ``address`` (an int: an array's ``.ctypes.data``), which it does not keep
    alive: the caller holds that array for as long as the view is used, and ``shape`` within it.

    An array handed to a kernel as its address costs the call an integer's conversion instead of an array's
    (its type looked up and its buffer unpacked), which a kernel handed a dozen arrays a call pays a dozen times."""
    if not isinstance(address, types.Integer) or not isinstance(dtype, types.NumberClass):
        return None
    if isinstance(shape, types.Integer):
        ndim = 1
    elif isinstance(shape, types.UniTuple) and isinstance(shape.dtype, types.Integer):
        ndim = shape.count
    else:
        return None
    array_type = types.Array(dtype.instance_type, ndim, "C")

    def codegen(context, builder, sig, args):
        if isinstance(sig.args[1], types.Integer):
            dims = [context.cast(builder, args[1], sig.args[1], types.intp)]
        else:
            dims = [
                context.cast(builder, v, sig.args[1].dtype, types.intp) for v in cgutils.unpack_tuple(builder, args[1])
            ]
        out = make_array(array_type)(context, builder)
        itemsize = context.get_constant(types.intp, context.get_abi_sizeof(context.get_data_type(array_type.dtype)))
        strides = [itemsize]
        for d in reversed(dims[1:]):
            strides.insert(0, builder.mul(strides[0], d))
        pointer = context.cast(builder, args[0], sig.args[0], types.intp)
        populate_array(
            out,
            data=builder.inttoptr(pointer, out.data.type),
            shape=cgutils.pack_array(builder, dims),
            strides=cgutils.pack_array(builder, strides),
            itemsize=itemsize,
            meminfo=None,
        )
        return out._getvalue()

    return array_type(address, shape, dtype), codegen


@intrinsic
def float32_from_bits(typingctx, pattern):
    """The float32 number whose bit pattern is the low 32 bits of the integer ``pattern``, as a float: the bits
    reinterpreted (one instruction, where building the number from its exponent and mantissa takes a libm call)."""
    if not isinstance(pattern, types.Integer):
        return None

    def codegen(context, builder, sig, args):
        bits = context.cast(builder, args[0], sig.args[0], types.uint32)
        return builder.fpext(builder.bitcast(bits, ir.FloatType()), ir.DoubleType())

    return types.float64(pattern), codegen
