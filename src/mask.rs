//! Operations on per-pixel masks (row-major) shared by labelling and training.

/// Connected components (4-neighbourhood) of equal values in a mask:
/// component index per pixel and, per component, its value, size and
/// whether it touches the image border.
pub(crate) struct Components {
    pub label: Vec<u32>,
    pub value: Vec<u16>,
    pub size: Vec<usize>,
    pub border: Vec<bool>,
}

pub(crate) fn components(mask: &[u16], w: usize, h: usize) -> Components {
    let mut c = Components {
        label: vec![u32::MAX; mask.len()],
        value: Vec::new(),
        size: Vec::new(),
        border: Vec::new(),
    };
    let mut stack = Vec::new();
    for start in 0..mask.len() {
        if c.label[start] != u32::MAX {
            continue;
        }
        let id = c.value.len() as u32;
        let v = mask[start];
        let (mut size, mut border) = (0, false);
        c.label[start] = id;
        stack.push(start);
        while let Some(i) = stack.pop() {
            size += 1;
            let (x, y) = (i % w, i / w);
            border |= x == 0 || y == 0 || x + 1 == w || y + 1 == h;
            let mut visit = |j: usize| {
                if c.label[j] == u32::MAX && mask[j] == v {
                    c.label[j] = id;
                    stack.push(j);
                }
            };
            if x > 0 {
                visit(i - 1);
            }
            if x + 1 < w {
                visit(i + 1);
            }
            if y > 0 {
                visit(i - w);
            }
            if y + 1 < h {
                visit(i + w);
            }
        }
        c.value.push(v);
        c.size.push(size);
        c.border.push(border);
    }
    c
}

/// `mask` (row-major, `width` x `height`) grown by `radius` pixels (Chebyshev), separably.
pub fn dilate_mask(mask: &[bool], width: u32, height: u32, radius: usize) -> Vec<bool> {
    let (w, h) = (width as usize, height as usize);
    if radius == 0 || mask.len() != w * h {
        return mask.to_vec();
    }
    let mut rows = vec![false; w * h];
    for y in 0..h {
        for x in 0..w {
            let (lo, hi) = (x.saturating_sub(radius), (x + radius).min(w - 1));
            rows[y * w + x] = mask[y * w + lo..=y * w + hi].iter().any(|&m| m);
        }
    }
    let mut out = vec![false; w * h];
    for y in 0..h {
        let (lo, hi) = (y.saturating_sub(radius), (y + radius).min(h - 1));
        for x in 0..w {
            out[y * w + x] = (lo..=hi).any(|yy| rows[yy * w + x]);
        }
    }
    out
}
