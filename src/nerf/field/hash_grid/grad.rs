//! Sparse-aware gradient buffer for the hash grid.
//!
//! `values` is dense (indexed like the grid's params) and allocated once;
//! a bitset with one bit per parameter records what backward touched, and a
//! summary bitset with one bit per 64-parameter word lets `clear`, `merge_from`
//! and `touched` visit only touched words, in ascending order.

/// Gradient of the grid's parameters plus the set of touched parameters.
///
/// Invariant: `values` is zero outside the touched parameters (it is written
/// by [`super::HashGrid::backward`], and reset by [`GridGrad::clear`]).
#[derive(Clone, Debug)]
pub struct GridGrad {
    /// Accumulated gradient, same indexing as `HashGrid::params`.
    pub values: Vec<f32>,
    /// One bit per parameter.
    pub(super) bits: Vec<u64>,
    /// One bit per word of `bits`.
    pub(super) summary: Vec<u64>,
}

impl GridGrad {
    /// Zeroed buffer for a grid with `param_count` parameters.
    ///
    /// Memory is written here so the pages are mapped before training starts.
    pub fn new(param_count: usize) -> GridGrad {
        let words = param_count.div_ceil(64);
        GridGrad {
            values: filled(param_count, 0.0),
            bits: filled(words, 0),
            summary: filled(words.div_ceil(64), 0),
        }
    }

    /// Number of parameters this buffer covers.
    pub fn param_count(&self) -> usize {
        self.values.len()
    }

    /// Adds `g` to the F parameters of table entry `e` and marks them in the
    /// per-parameter bitset; [`GridGrad::mark_summary`] must follow.
    #[inline(always)]
    pub(crate) fn add_entry<const F: usize>(&mut self, e: usize, g: &[f32; F]) {
        let p = e * F;
        let v = &mut self.values[p..p + F];
        for f in 0..F {
            v[f] += g[f];
        }
        // F divides 64, so an entry's bits never straddle two words. An
        // unconditional OR beats testing first (the branch mispredicts).
        self.bits[p >> 6] |= (u64::MAX >> (64 - F)) << (p & 63);
    }

    /// Records in the summary the non-zero words of `bits` in `lo..=hi`
    /// (kept out of `add_entry`, where its read-modify-writes cost 25%).
    pub(crate) fn mark_summary(&mut self, lo: usize, hi: usize) {
        if self.bits.is_empty() || lo > hi {
            return;
        }
        let hi = hi.min(self.bits.len() - 1);
        for s in lo >> 6..=hi >> 6 {
            // Branch-free: whether a word is touched is unpredictable.
            let mut mask = 0u64;
            for w in lo.max(s * 64)..=hi.min(s * 64 + 63) {
                mask |= ((self.bits[w] != 0) as u64) << (w & 63);
            }
            self.summary[s] |= mask;
        }
    }

    /// Touched parameter indices since the last clear, ascending, without repeats.
    pub fn touched(&self) -> impl Iterator<Item = usize> + '_ {
        self.touched_words()
            .flat_map(|(first, bits)| ones(bits).map(move |b| first + b))
    }

    /// Touched parameters as `(first index, bitmask)` over 64-parameter words,
    /// ascending: bit b set means parameter `first + b` was touched.
    pub fn touched_words(&self) -> impl Iterator<Item = (usize, u64)> + '_ {
        self.touched_word_indices().map(|w| (w * 64, self.bits[w]))
    }

    /// Touched parameter indices in `start..start + len`, ascending;
    /// `start` and `len` are multiples of [`GridGrad::BLOCK`], so that each
    /// block's parameters can be updated by another thread.
    pub fn touched_in(&self, start: usize, len: usize) -> impl Iterator<Item = usize> + '_ {
        self.touched_words_in(start, len)
            .flat_map(|(first, bits)| ones(bits).map(move |b| first + b))
    }

    /// [`GridGrad::touched_in`] as `(first index, bitmask)` words.
    pub fn touched_words_in(&self, start: usize, len: usize) -> impl Iterator<Item = (usize, u64)> + '_ {
        Touched {
            bits: &self.bits,
            summary: &self.summary,
        }
        .words_in(start, len)
    }

    /// Root mean square of the touched values, or `None` when one of them
    /// is not finite; word by word on every thread (untouched values are
    /// zero, so whole words can be summed).
    pub fn touched_rms(&self) -> Option<f32> {
        use rayon::prelude::*;
        // Fixed chunks, partial sums added in order: the same sum on any
        // number of threads.
        const SUMMARY_WORDS: usize = 16;
        let partials: Vec<(f64, usize, bool)> = self
            .summary
            .par_chunks(SUMMARY_WORDS)
            .enumerate()
            .map(|(c, chunk)| {
                let (mut sum, mut count, mut finite) = (0.0f64, 0usize, true);
                let words = chunk
                    .iter()
                    .enumerate()
                    .flat_map(|(k, &sw)| ones(sw).map(move |b| (c * SUMMARY_WORDS + k) * 64 + b));
                for w in words {
                    let end = (w * 64 + 64).min(self.values.len());
                    let squares = sum_of_squares(&self.values[w * 64..end]);
                    finite &= squares.is_finite();
                    sum += squares as f64;
                    count += self.bits[w].count_ones() as usize;
                }
                (sum, count, finite)
            })
            .collect();
        let (sum, count, finite) = partials
            .iter()
            .fold((0.0, 0, true), |a, b| (a.0 + b.0, a.1 + b.1, a.2 && b.2));
        finite.then(|| (sum / count.max(1) as f64).sqrt() as f32)
    }

    /// Parameters covered by one summary word (64 words of 64).
    pub const BLOCK: usize = 64 * 64;

    /// Number of touched parameters.
    pub fn touched_count(&self) -> usize {
        self.touched_words().map(|(_, b)| b.count_ones() as usize).sum()
    }

    /// Zeroes the touched values and forgets them; cost follows what was touched.
    pub fn clear(&mut self) {
        for s in 0..self.summary.len() {
            let mut sw = self.summary[s];
            while sw != 0 {
                let w = s * 64 + sw.trailing_zeros() as usize;
                sw &= sw - 1;
                let end = (w * 64 + 64).min(self.values.len());
                self.values[w * 64..end].fill(0.0);
                self.bits[w] = 0;
            }
            self.summary[s] = 0;
        }
    }

    /// Adds `other`'s touched values into `self`, takes over its touched set
    /// and leaves `other` empty (its values zeroed while they are in cache,
    /// so its next [`GridGrad::clear`] has nothing to do). Deterministic for
    /// a fixed merge order. Panics if the sizes differ.
    pub fn drain_from(&mut self, other: &mut GridGrad) {
        assert_eq!(
            self.values.len(),
            other.values.len(),
            "GridGrad::drain_from: buffers of different grids"
        );
        use rayon::prelude::*;
        // Blocks of summary words on every thread (disjoint parameters).
        const SUMMARY_WORDS: usize = 16;
        let GridGrad {
            values: from_values,
            bits: from_bits,
            summary: from_summary,
        } = other;
        self.values
            .par_chunks_mut(SUMMARY_WORDS * Self::BLOCK)
            .zip(self.bits.par_chunks_mut(SUMMARY_WORDS * 64))
            .zip(from_values.par_chunks_mut(SUMMARY_WORDS * Self::BLOCK))
            .zip(from_bits.par_chunks_mut(SUMMARY_WORDS * 64))
            .zip(from_summary.par_chunks(SUMMARY_WORDS))
            .for_each(|((((values, bits), from_values), from_bits), summary)| {
                for (k, &sw) in summary.iter().enumerate() {
                    for w in ones(sw).map(|b| k * 64 + b) {
                        let (start, end) = (w * 64, (w * 64 + 64).min(values.len()));
                        // Untouched values of `other` are zero, so adding the whole word is exact.
                        for (a, b) in values[start..end].iter_mut().zip(&mut from_values[start..end]) {
                            *a += *b;
                            *b = 0.0;
                        }
                        bits[w] |= std::mem::take(&mut from_bits[w]);
                    }
                }
            });
        for (a, b) in self.summary.iter_mut().zip(from_summary.iter_mut()) {
            *a |= std::mem::take(b);
        }
    }

    /// The values (to be read and zeroed by the optimiser) beside the touched
    /// set, which stays readable; call [`GridGrad::forget_zeroed`] once every
    /// touched value is zero again.
    pub fn values_and_touched(&mut self) -> (&mut [f32], Touched<'_>) {
        let touched = Touched {
            bits: &self.bits,
            summary: &self.summary,
        };
        (&mut self.values, touched)
    }

    /// Forgets the touched set once its values were zeroed by whoever
    /// consumed them (see [`GridGrad::values_and_touched`]): restores the
    /// invariant without writing the values a second time.
    pub fn forget_zeroed(&mut self) {
        for s in 0..self.summary.len() {
            let mut sw = std::mem::take(&mut self.summary[s]);
            while sw != 0 {
                let w = s * 64 + sw.trailing_zeros() as usize;
                sw &= sw - 1;
                debug_assert!(
                    self.values[w * 64..(w * 64 + 64).min(self.values.len())]
                        .iter()
                        .all(|v| *v == 0.0),
                    "GridGrad::forget_zeroed: word {w} still holds values"
                );
                self.bits[w] = 0;
            }
        }
    }

    /// Indices of words of `bits` with a touched parameter, ascending.
    fn touched_word_indices(&self) -> impl Iterator<Item = usize> + '_ {
        self.summary
            .iter()
            .enumerate()
            .flat_map(|(s, &sw)| ones(sw).map(move |b| s * 64 + b))
    }
}

/// A gradient buffer's touched set, read beside its values.
#[derive(Clone, Copy)]
pub struct Touched<'a> {
    bits: &'a [u64],
    summary: &'a [u64],
}

impl<'a> Touched<'a> {
    /// Touched parameters in `start..start + len` as `(first index,
    /// bitmask)` words, ascending; `start` and `len` are multiples of
    /// [`GridGrad::BLOCK`], so that each block's parameters can be updated
    /// by another thread.
    pub fn words_in(self, start: usize, len: usize) -> impl Iterator<Item = (usize, u64)> + 'a {
        debug_assert!(start.is_multiple_of(GridGrad::BLOCK) && len.is_multiple_of(GridGrad::BLOCK));
        let first = start / GridGrad::BLOCK;
        let last = ((start + len) / GridGrad::BLOCK).min(self.summary.len());
        let bits = self.bits;
        self.summary[first.min(last)..last]
            .iter()
            .enumerate()
            .flat_map(move |(k, &sw)| ones(sw).map(move |b| (first + k) * 64 + b))
            .map(move |w| (w * 64, bits[w]))
    }
}

/// Sum of the squares of `values` in eight interleaved partial sums, so that
/// the additions do not wait on one another (a fixed order: the same sum on
/// every run).
fn sum_of_squares(values: &[f32]) -> f32 {
    let mut partial = [0.0f32; 8];
    let mut lanes = values.chunks_exact(8);
    for lane in &mut lanes {
        for k in 0..8 {
            partial[k] += lane[k] * lane[k];
        }
    }
    let rest: f32 = lanes.remainder().iter().map(|v| v * v).sum();
    partial.iter().sum::<f32>() + rest
}

/// Positions of the set bits of `word`, ascending.
fn ones(mut word: u64) -> impl Iterator<Item = usize> {
    std::iter::from_fn(move || {
        if word == 0 {
            return None;
        }
        let b = word.trailing_zeros() as usize;
        word &= word - 1;
        Some(b)
    })
}

/// A vector of `n` copies of `v`, written element by element so that its pages
/// are mapped now rather than on first use in the training loop.
fn filled<T: Copy>(n: usize, v: T) -> Vec<T> {
    let mut out = Vec::with_capacity(n);
    // Opaque value: keeps LLVM from turning the fill into a lazily mapped calloc.
    out.resize(n, std::hint::black_box(v));
    out
}
