# The C extension diffquat/_kernels.c. The kernels take integer arguments only (data pointers, strides
# in elements, sizes and flags); diffquat/torch/_cpu.py is their only caller. xla_handlers gives the
# same kernels as XLA FFI handlers, for diffquat/jax/_xla.py, and xla_set_tables hands those the
# series tables that the torch binding passes with each call.
from typing import Any

def q2m_forward(
    dtype: int, threads: int, n: int, first: int, q: int, q_row: int, q_component: int, out: int, /
) -> None: ...
def q2m_backward(
    dtype: int,
    threads: int,
    n: int,
    first: int,
    q: int,
    q_row: int,
    q_component: int,
    grad: int,
    grad_row: int,
    grad_i: int,
    grad_j: int,
    out: int,
    /,
) -> None: ...
def m2q_forward(
    dtype: int, threads: int, n: int, first: int, m: int, m_row: int, m_i: int, m_j: int, out: int, /
) -> None: ...
def m2q_backward(
    dtype: int,
    threads: int,
    n: int,
    first: int,
    m: int,
    m_row: int,
    m_i: int,
    m_j: int,
    q: int,
    q_row: int,
    q_component: int,
    grad: int,
    grad_row: int,
    grad_component: int,
    out: int,
    /,
) -> None: ...
def jac_forward(
    dtype: int,
    threads: int,
    n: int,
    kind: int,
    w: int,
    w_row: int,
    w_component: int,
    series: int,
    terms0: int,
    terms1: int,
    terms2: int,
    out: int,
    /,
) -> None: ...
def jac_backward(
    dtype: int,
    threads: int,
    n: int,
    kind: int,
    w: int,
    w_row: int,
    w_component: int,
    grad: int,
    grad_row: int,
    grad_i: int,
    grad_j: int,
    series: int,
    terms0: int,
    terms1: int,
    terms2: int,
    out: int,
    /,
) -> None: ...
def qplus_forward(
    dtype: int,
    threads: int,
    n: int,
    first: int,
    right: int,
    q: int,
    q_row: int,
    q_component: int,
    d: int,
    d_row: int,
    d_component: int,
    table: int,
    out: int,
    /,
) -> None: ...
def qplus_backward(
    dtype: int,
    threads: int,
    n: int,
    first: int,
    right: int,
    q: int,
    q_row: int,
    q_component: int,
    d: int,
    d_row: int,
    d_component: int,
    grad: int,
    grad_row: int,
    grad_component: int,
    table: int,
    out_q: int,
    out_d: int,
    /,
) -> None: ...
def xla_handlers() -> dict[str, Any]: ...
def xla_set_tables(
    f64: int, series: int, n_series: int, terms0: int, terms1: int, terms2: int, exp_table: int, /
) -> None: ...

PORTABLE: int  # 1 for the scalar build the tests make (DIFFQUAT_PORTABLE), 0 for the installed one
