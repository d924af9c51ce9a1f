//! Memory hints and loads the walks share: prefetching a node, its children line or any
//! value (x86 hints; nothing elsewhere), and an instance transform's packed columns in
//! four SSE loads.
#![cfg_attr(
    target_arch = "x86_64",
    expect(
        unsafe_code,
        reason = "prefetch hints and unaligned SSE loads are intrinsics on raw pointers"
    )
)]

use crate::accel::bvh::WideNode;
use glam::Affine3A;
#[cfg(target_arch = "x86_64")]
use std::arch::x86_64::*;

/// Starts loading all four cache lines of `node` into the cache (SSE, so any x86-64).
#[cfg(target_arch = "x86_64")]
#[inline(always)]
pub fn prefetch_node(node: &WideNode) {
    let base = std::ptr::from_ref(node).cast::<i8>();
    for line in 0..std::mem::size_of::<WideNode>() / 64 {
        // SAFETY: a prefetch is a hint that never faults, and the address lies
        // inside `node`.
        unsafe { _mm_prefetch::<_MM_HINT_T0>(base.add(line * 64)) };
    }
}

/// Starts loading the cache line of `node`'s child references and counts (its last:
/// a node is 64-byte aligned), which its visit reads only after the box test.
#[cfg(target_arch = "x86_64")]
#[inline(always)]
pub fn prefetch_children(node: &WideNode) {
    // SAFETY: a prefetch is a hint that never faults, and the address lies inside
    // `node`.
    unsafe { _mm_prefetch::<_MM_HINT_T0>(std::ptr::from_ref(&node.children).cast::<i8>()) };
}

/// Starts loading every cache line of `value` (SSE, so any x86-64): for gathers in an
/// order unrelated to memory, where each load misses.
#[cfg(target_arch = "x86_64")]
#[inline(always)]
pub fn prefetch<T>(value: &T) {
    let first = std::ptr::from_ref(value).cast::<i8>();
    let last = std::mem::size_of::<T>().max(1) - 1;
    // SAFETY: a prefetch is a hint that never faults; every address lies inside
    // `value` (for a zero-sized one the first is a valid dangling address).
    unsafe {
        let mut offset = 0;
        while offset < last {
            _mm_prefetch::<_MM_HINT_T0>(first.add(offset));
            offset += 64;
        }
        _mm_prefetch::<_MM_HINT_T0>(first.add(last));
    }
}

/// The transform whose twelve column values (x axis, y axis, z axis, translation)
/// start `columns`, in four unaligned 16-byte loads (SSE2, so any x86-64) instead of
/// twelve scalar inserts: each column's fourth lane holds the next value, which
/// `Vec3A` leaves unused (the thirteenth value exists so the last load stays inside
/// the array).
#[cfg(target_arch = "x86_64")]
#[inline(always)]
pub fn affine_from_columns(columns: &[f32; 13]) -> Affine3A {
    let base = columns.as_ptr();
    // SAFETY: each load reads four f32 at offsets 0, 3, 6 and 9 of thirteen.
    let column = |at: usize| glam::Vec3A::from(unsafe { _mm_loadu_ps(base.add(at)) });
    Affine3A::from_cols(column(0), column(3), column(6), column(9))
}

/// The transform whose twelve column values (x axis, y axis, z axis, translation) start
/// `columns`; the thirteenth value only pads the last load. The same bits as
/// `Affine3A::from_cols_array` in the columns' lanes.
#[cfg(not(target_arch = "x86_64"))]
#[inline(always)]
pub fn affine_from_columns(columns: &[f32; 13]) -> Affine3A {
    Affine3A::from_cols_slice(&columns[..12])
}

/// Prefetching is an x86 hint here; elsewhere nothing.
#[cfg(not(target_arch = "x86_64"))]
#[inline(always)]
pub fn prefetch_node(_node: &WideNode) {}

/// Prefetching is an x86 hint here; elsewhere nothing.
#[cfg(not(target_arch = "x86_64"))]
#[inline(always)]
pub fn prefetch<T>(_value: &T) {}

/// Prefetching is an x86 hint here; elsewhere nothing.
#[cfg(not(target_arch = "x86_64"))]
#[inline(always)]
pub fn prefetch_children(_node: &WideNode) {}
