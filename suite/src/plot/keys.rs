//! Where each point's key goes: beside its marker, clear of the other keys and markers where a place is free.
//!
//! A greedy placement, as map labellers do it: the points are taken in the order given (the best-ranked first, so
//! they get the nearest places), and each key tries rings of places around its marker, nearest ring first, taking
//! the first place that overlaps no key placed before it, no marker, and nothing outside the plotting area. When no
//! place is free it takes the one that overlaps least. A key set off beyond the first ring is drawn with a leader
//! line back to its marker, so that it still reads as that point's.

/// A rectangle in pixels, `right` and `bottom` exclusive.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct PixelBox {
    pub left: i32,
    pub top: i32,
    pub right: i32,
    pub bottom: i32,
}

impl PixelBox {
    /// The box of `size` (width, height) centred on `centre`.
    pub fn centred(centre: (i32, i32), size: (i32, i32)) -> PixelBox {
        let left = centre.0 - size.0 / 2;
        let top = centre.1 - size.1 / 2;
        PixelBox {
            left,
            top,
            right: left + size.0,
            bottom: top + size.1,
        }
    }

    fn area(&self) -> i64 {
        i64::from((self.right - self.left).max(0)) * i64::from((self.bottom - self.top).max(0))
    }

    /// The area the two boxes share.
    pub fn overlap(&self, other: &PixelBox) -> i64 {
        let width = (self.right.min(other.right) - self.left.max(other.left)).max(0);
        let height = (self.bottom.min(other.bottom) - self.top.max(other.top)).max(0);
        i64::from(width) * i64::from(height)
    }

    /// The point of the box nearest to `p` (`p` itself when inside): where a leader line meets the key.
    pub fn nearest(&self, p: (i32, i32)) -> (i32, i32) {
        (
            p.0.clamp(self.left, self.right - 1),
            p.1.clamp(self.top, self.bottom - 1),
        )
    }
}

/// One key's place: its box, and whether it is far enough from its marker to need a leader line.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Placed {
    pub at: PixelBox,
    pub leader: bool,
}

/// Rings tried around a marker before settling for the least-overlapping place.
const RINGS: i32 = 8;

/// The directions tried on each ring, in order of preference: to the right (where a reader looks first), then
/// above and below it, left, and the diagonals on the left.
const DIRECTIONS: [(i32, i32); 8] = [(1, 0), (1, -1), (1, 1), (-1, 0), (0, -1), (0, 1), (-1, -1), (-1, 1)];

/// Places the key of each marker (`markers[i]`, a centre in pixels, whose key measures `sizes[i]`) inside `area`.
/// Markers are drawn `marker_radius` pixels around their centres, and no key may cover one.
pub fn place_keys(markers: &[(i32, i32)], sizes: &[(i32, i32)], area: PixelBox, marker_radius: i32) -> Vec<Placed> {
    let marker_boxes: Vec<PixelBox> = markers
        .iter()
        .map(|&m| PixelBox::centred(m, (2 * marker_radius + 1, 2 * marker_radius + 1)))
        .collect();
    let mut placed: Vec<Placed> = Vec::with_capacity(markers.len());
    for (&marker, &size) in markers.iter().zip(sizes) {
        // What a candidate place costs: the area it shares with keys placed before it and with markers, and, four
        // times over, its area outside the plotting area (a key cut off by the edge is the worst outcome).
        let cost = |candidate: &PixelBox| -> i64 {
            let keys: i64 = placed.iter().map(|p| p.at.overlap(candidate)).sum();
            let covered: i64 = marker_boxes.iter().map(|m| m.overlap(candidate)).sum();
            let outside = candidate.area() - candidate.overlap(&area);
            keys + covered + 4 * outside
        };
        // The ring's gap between the marker's edge and the key grows by a key's height from ring to ring.
        let step = size.1.max(1);
        let mut best: Option<(i64, i32, PixelBox)> = None;
        'rings: for ring in 0..RINGS {
            let gap = marker_radius + 2 + ring * step;
            for (dx, dy) in DIRECTIONS {
                let centre = (marker.0 + dx * (gap + size.0 / 2), marker.1 + dy * (gap + size.1 / 2));
                let candidate = PixelBox::centred(centre, size);
                let c = cost(&candidate);
                if best.is_none_or(|(b, _, _)| c < b) {
                    best = Some((c, ring, candidate));
                }
                if c == 0 {
                    break 'rings;
                }
            }
        }
        let (_, ring, at) = best.expect("at least one ring and direction are tried");
        placed.push(Placed { at, leader: ring > 0 });
    }
    placed
}

#[cfg(test)]
mod tests {
    use super::*;

    const AREA: PixelBox = PixelBox {
        left: 0,
        top: 0,
        right: 400,
        bottom: 300,
    };

    #[test]
    fn a_lone_key_sits_right_of_its_marker_without_a_leader() {
        let placed = place_keys(&[(100, 100)], &[(14, 12)], AREA, 5);
        assert_eq!(placed.len(), 1);
        let at = placed[0].at;
        assert!(!placed[0].leader);
        assert!(at.left > 105 && at.left < 115, "{at:?}");
        assert!(at.top <= 100 && at.bottom > 100, "{at:?}");
    }

    #[test]
    fn keys_of_a_tight_cluster_do_not_overlap_each_other_or_any_marker() {
        // Twelve markers within a few pixels of each other, as entries with nearly equal scores are drawn.
        let markers: Vec<(i32, i32)> = (0..12).map(|i| (200 + (i % 3) * 3, 150 + (i / 3) * 2)).collect();
        let sizes: Vec<(i32, i32)> = (0..12).map(|i| (if i < 9 { 8 } else { 14 }, 12)).collect();
        let placed = place_keys(&markers, &sizes, AREA, 5);
        for (i, a) in placed.iter().enumerate() {
            assert_eq!(a.at.overlap(&AREA), a.at.area(), "key {i} leaves the area: {a:?}");
            for (j, b) in placed.iter().enumerate().skip(i + 1) {
                assert_eq!(a.at.overlap(&b.at), 0, "keys {i} and {j} overlap: {a:?} {b:?}");
            }
            for (j, &m) in markers.iter().enumerate() {
                assert_eq!(
                    a.at.overlap(&PixelBox::centred(m, (11, 11))),
                    0,
                    "key {i} covers marker {j}"
                );
            }
        }
        // The first keys get the nearest places; later ones are set off, with leader lines.
        assert!(!placed[0].leader);
        assert!(placed.iter().any(|p| p.leader));
    }

    #[test]
    fn a_key_at_the_right_edge_goes_left_instead_of_being_cut_off() {
        let placed = place_keys(&[(396, 150)], &[(30, 12)], AREA, 5);
        let at = placed[0].at;
        assert!(at.right <= 396 && at.left >= 0, "{at:?}");
        assert!(!placed[0].leader);
    }
}
