//! Sorting one row of neighbour indices (distinct u32 values): bitonic networks on 128-bit
//! registers for rows of up to 32, a rank sort for up to 48, the standard sort beyond.

use super::simd::has_avx2;

/// Writes the distinct values `row` in ascending order to `out` (same length).
/// A typical row holds ~10-40 neighbours; for those, placing each value at its rank
/// (the count of smaller values) is branch-free and vectorises, where a comparison sort
/// pays a misprediction per element.
#[inline(always)]
fn sort_into(row: &mut [u32], out: &mut [u32]) {
    const SHORT: usize = 48;
    #[cfg(target_arch = "x86_64")]
    if row.len() <= SHORT && has_avx2() {
        // SAFETY: checked that the CPU has AVX2 (the check is a cached load).
        unsafe { rank_sort_avx2(row, out) };
        return;
    }
    if row.len() <= SHORT {
        // Padded to whole vectors with values no index can exceed, so the rank loop has no
        // scalar tail.
        let mut padded = [u32::MAX; SHORT];
        padded[..row.len()].copy_from_slice(row);
        let width = row.len().div_ceil(8) * 8;
        for &x in row.iter() {
            let rank: u32 = padded[..width].iter().map(|&y| (y < x) as u32).sum();
            out[rank as usize] = x;
        }
    } else {
        row.sort_unstable();
        out.copy_from_slice(row);
    }
}

/// Sorts the distinct values buf[..n] in place; buf holds at least 32 values past
/// buf[..n] (ROW_SLACK), which the networks may overwrite.
#[inline(always)]
pub(super) fn sort_in_place(avx2: bool, buf: &mut [u32], n: usize) {
    #[cfg(target_arch = "x86_64")]
    if avx2 && n <= 32 {
        assert!(buf.len() >= 32);
        // SAFETY: avx2 is only true when the CPU has AVX2; buf holds 32 values.
        unsafe { network_sort_32(buf.as_mut_ptr(), n) };
        return;
    }
    let _ = avx2;
    if n <= 48 {
        let mut row = [0u32; 48];
        row[..n].copy_from_slice(&buf[..n]);
        sort_into(&mut row[..n], &mut buf[..n]);
    } else {
        buf[..n].sort_unstable();
    }
}

/// The usual row (at most 32 values; ~14 on average) sorted by a bitonic network on
/// 128-bit registers: the same steps whatever the values, so no branch for the predictor to
/// miss but the one on the width (16 or 32), and no 256-bit shuffles (slow on Zen 1). It beat
/// a rank sort (count of smaller values, 8 lanes at a time) by about 2x in instructions.
/// Lanes past n are padded with u32::MAX, so up to 32 values are written.
///
/// # Safety
/// p is valid for 32 values; the values p[..n] are distinct and below u32::MAX.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
#[inline]
unsafe fn network_sort_32(p: *mut u32, n: usize) {
    if n <= 16 {
        let mut r = load_padded::<4>(p, n);
        sort16(&mut r);
        store_regs(p, &r);
    } else {
        let mut r = load_padded::<8>(p, n);
        let (lo, hi) = r.split_at_mut(4);
        sort16(lo.try_into().unwrap());
        sort16(hi.try_into().unwrap());
        merge_sorted::<8>(&mut r);
        store_regs(p, &r);
    }
}

#[cfg(target_arch = "x86_64")]
use std::arch::x86_64::__m128i;

/// M registers of 4 values from p, lanes from n on set to u32::MAX.
#[cfg(target_arch = "x86_64")]
#[inline(always)]
unsafe fn load_padded<const M: usize>(p: *const u32, n: usize) -> [__m128i; M] {
    use std::arch::x86_64::*;
    let last = _mm_set1_epi32(n as i32 - 1);
    let lane = _mm_setr_epi32(0, 1, 2, 3);
    let mut r = [_mm_setzero_si128(); M];
    for (k, rk) in r.iter_mut().enumerate() {
        let past = _mm_cmpgt_epi32(_mm_add_epi32(lane, _mm_set1_epi32(4 * k as i32)), last);
        *rk = _mm_or_si128(_mm_loadu_si128(p.add(4 * k) as *const __m128i), past);
    }
    r
}

#[cfg(target_arch = "x86_64")]
#[inline(always)]
unsafe fn store_regs<const M: usize>(p: *mut u32, r: &[__m128i; M]) {
    use std::arch::x86_64::*;
    for (k, rk) in r.iter().enumerate() {
        _mm_storeu_si128(p.add(4 * k) as *mut __m128i, *rk);
    }
}

/// Compare-exchange, lane by lane: a gets the smaller values, b the larger.
#[cfg(target_arch = "x86_64")]
#[inline(always)]
unsafe fn cmp_swap(r: &mut [__m128i], a: usize, b: usize) {
    use std::arch::x86_64::*;
    let lo = _mm_min_epu32(r[a], r[b]);
    r[b] = _mm_max_epu32(r[a], r[b]);
    r[a] = lo;
}

/// Sorts a bitonic sequence of 4 held in one register.
#[cfg(target_arch = "x86_64")]
#[inline(always)]
unsafe fn bitonic4(x: __m128i) -> __m128i {
    use std::arch::x86_64::*;
    // Lanes (0, 2), (1, 3), then (0, 1), (2, 3).
    let t = _mm_shuffle_epi32::<0x4E>(x);
    let x = _mm_blend_epi32::<0b1100>(_mm_min_epu32(x, t), _mm_max_epu32(x, t));
    let t = _mm_shuffle_epi32::<0xB1>(x);
    _mm_blend_epi32::<0b1010>(_mm_min_epu32(x, t), _mm_max_epu32(x, t))
}

/// Sorts a bitonic sequence held in M registers (M a power of two), in place.
#[cfg(target_arch = "x86_64")]
#[inline(always)]
unsafe fn bitonic_merge(r: &mut [__m128i]) {
    let m = r.len();
    let mut s = m / 2;
    while s >= 1 {
        for i in 0..m {
            if i & s == 0 {
                cmp_swap(r, i, i + s);
            }
        }
        s /= 2;
    }
    for x in r.iter_mut() {
        *x = bitonic4(*x);
    }
}

/// Merges the sorted halves r[..M/2] and r[M/2..] into one sorted sequence.
#[cfg(target_arch = "x86_64")]
#[inline(always)]
unsafe fn merge_sorted<const M: usize>(r: &mut [__m128i; M]) {
    use std::arch::x86_64::*;
    let h = M / 2;
    // The first half ascending and the second reversed form a bitonic sequence; one
    // compare-exchange of opposite lanes splits it into a lower and an upper bitonic half.
    let second: [__m128i; M] = std::array::from_fn(|i| {
        if i < h {
            _mm_shuffle_epi32::<0x1B>(r[M - 1 - i])
        } else {
            _mm_setzero_si128()
        }
    });
    for i in 0..h {
        let (a, b) = (r[i], second[i]);
        r[i] = _mm_min_epu32(a, b);
        r[h + i] = _mm_max_epu32(a, b);
    }
    let (lo, hi) = r.split_at_mut(h);
    bitonic_merge(lo);
    bitonic_merge(hi);
}

/// Sorts 16 values in 4 registers: each lane's column by a 4-input network, a transpose
/// (each register then holds a sorted run of 4), and two rounds of merges.
#[cfg(target_arch = "x86_64")]
#[inline(always)]
unsafe fn sort16(r: &mut [__m128i; 4]) {
    use std::arch::x86_64::*;
    for (a, b) in [(0, 1), (2, 3), (0, 2), (1, 3), (1, 2)] {
        cmp_swap(r, a, b);
    }
    let t0 = _mm_unpacklo_epi32(r[0], r[1]);
    let t1 = _mm_unpackhi_epi32(r[0], r[1]);
    let t2 = _mm_unpacklo_epi32(r[2], r[3]);
    let t3 = _mm_unpackhi_epi32(r[2], r[3]);
    r[0] = _mm_unpacklo_epi64(t0, t2);
    r[1] = _mm_unpackhi_epi64(t0, t2);
    r[2] = _mm_unpacklo_epi64(t1, t3);
    r[3] = _mm_unpackhi_epi64(t1, t3);
    let (lo, hi) = r.split_at_mut(2);
    merge_sorted::<2>(lo.try_into().unwrap());
    merge_sorted::<2>(hi.try_into().unwrap());
    merge_sorted::<4>(r);
}

/// [`sort_into`] for rows of at most 48: the rank of each value is the count of smaller
/// values, worked out for 8 values at once: each value in turn is broadcast and compared with
/// every vector of the row (indices are biased by 2^31 for the signed compare).
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
unsafe fn rank_sort_avx2(row: &[u32], out: &mut [u32]) {
    assert!(row.len() <= 48 && out.len() == row.len());
    // A fixed vector count keeps the row and its ranks in registers.
    match row.len().div_ceil(8) {
        0 => {}
        1 => rank_sort_vectors::<1>(row, out),
        2 => rank_sort_vectors::<2>(row, out),
        3 => rank_sort_vectors::<3>(row, out),
        4 => rank_sort_vectors::<4>(row, out),
        5 => rank_sort_vectors::<5>(row, out),
        _ => rank_sort_vectors::<6>(row, out),
    }
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
#[inline]
unsafe fn rank_sort_vectors<const NV: usize>(row: &[u32], out: &mut [u32]) {
    use std::arch::x86_64::*;
    // Lanes 0..r of a masked load are MASK_WINDOW[8 - r..16 - r].
    static MASK_WINDOW: [i32; 16] = [-1, -1, -1, -1, -1, -1, -1, -1, 0, 0, 0, 0, 0, 0, 0, 0];
    let m = row.len();
    debug_assert!(m.div_ceil(8) == NV && out.len() == m);
    let bias = _mm256_set1_epi32(i32::MIN);
    let mut v = [_mm256_setzero_si256(); NV];
    for (k, vk) in v.iter_mut().enumerate() {
        // A masked load reads only the lanes of the row, never past its end; the padding
        // lanes get ranks too, which are never read.
        let lanes = (m - 8 * k).min(8);
        let mask = _mm256_loadu_si256(MASK_WINDOW.as_ptr().add(8 - lanes) as *const __m256i);
        let x = _mm256_maskload_epi32(row.as_ptr().add(8 * k) as *const i32, mask);
        *vk = _mm256_xor_si256(x, bias);
    }
    let mut rank = [_mm256_setzero_si256(); NV];
    for &x in row {
        let xb = _mm256_set1_epi32((x ^ 0x8000_0000) as i32);
        for k in 0..NV {
            // -1 in the lanes whose value is greater than x: x counts as smaller there.
            rank[k] = _mm256_sub_epi32(rank[k], _mm256_cmpgt_epi32(v[k], xb));
        }
    }
    let mut ranks = [[0u32; 8]; NV];
    for k in 0..NV {
        _mm256_storeu_si256(ranks[k].as_mut_ptr() as *mut __m256i, rank[k]);
    }
    for (&x, &r) in row.iter().zip(ranks.as_flattened()) {
        // The values are distinct indices, so the ranks are a permutation of 0..m.
        *out.get_unchecked_mut(r as usize) = x;
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn rank_sort_and_comparison_sort_agree() {
        let row: Vec<u32> = (0..47u32)
            .map(|k| k.wrapping_mul(2_654_435_761) ^ 0x8000_0003)
            .collect();
        for len in [0, 1, 7, 8, 9, 31, 47] {
            let mut want = row[..len].to_vec();
            want.sort_unstable();
            let mut got = vec![0u32; len];
            sort_into(&mut row[..len].to_vec(), &mut got);
            assert_eq!(got, want);
            #[cfg(target_arch = "x86_64")]
            if has_avx2() {
                let mut wide = vec![0u32; len];
                unsafe { rank_sort_avx2(&row[..len], &mut wide) };
                assert_eq!(wide, want);
            }
        }
    }

    #[test]
    fn in_place_sorts_agree_with_the_standard_sort() {
        // Every width path (network 16 and 32, rank sort, comparison sort), values spanning
        // the whole unsigned range (the networks compare unsigned), garbage past the row.
        let mut s = 0x9E37_79B9_7F4A_7C15u64;
        for n in (0..=70).chain([100, 300]) {
            for avx2 in [false, has_avx2()] {
                for round in 0..20 {
                    let mut set = std::collections::BTreeSet::new();
                    while set.len() < n {
                        s ^= s << 13;
                        s ^= s >> 7;
                        s ^= s << 17;
                        let v = match round % 3 {
                            0 if n <= 64 => s as u32 % 64,
                            1 if n <= 64 => u32::MAX - 1 - (s as u32 % 100),
                            _ => (s as u32).min(u32::MAX - 1),
                        };
                        set.insert(v);
                    }
                    let want: Vec<u32> = set.iter().copied().collect();
                    let mut row: Vec<u32> = want.iter().rev().copied().collect();
                    row.rotate_left(n / 3);
                    // The room past every row that the rows' buffers keep (ROW_SLACK).
                    row.extend(std::iter::repeat_n(7, 32));
                    sort_in_place(avx2, &mut row, n);
                    assert_eq!(&row[..n], &want[..], "n {n} avx2 {avx2} round {round}");
                }
            }
        }
    }
}
