//! Behaviour trees as pictures: Graphviz DOT text and a self-contained SVG.
//!
//! Why this exists: the indented text of [`Bt::render`] is fine for a PPA of ten nodes,
//! but a Multi-GEESE member with its controllers in place has a hundred, and a figure
//! of an evolved tree is what a reader of the paper compares. DOT hands the tree to
//! Graphviz when it is installed; the SVG needs nothing at run time, so it is drawn
//! here with a small tidy layout: every subtree gets its own horizontal band (so the
//! leaves come out on a row, left to right in tick order, and nothing overlaps), parents
//! are centred over their children, and each level is one row. Composite nodes are
//! white boxes, the Inverter decorator a grey one, leaves rounded boxes coloured by the
//! grammar tag they came from (post-condition, pre-condition, constraint, action).
//! Labels are the text rendering's, and every piece of text is escaped.
use super::{Bt, Kind, Tag};
use std::fmt::Write;

/// How a tree is printed (`geese grammar tree --format`).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum TreeFormat {
    /// [`Bt::render`]'s indented listing.
    #[default]
    Text,
    /// A Graphviz digraph.
    Dot,
    /// A self-contained SVG drawing.
    Svg,
}

impl std::str::FromStr for TreeFormat {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        match s {
            "text" => Ok(TreeFormat::Text),
            "dot" => Ok(TreeFormat::Dot),
            "svg" => Ok(TreeFormat::Svg),
            other => Err(format!("unknown tree format '{other}' (expected text, dot or svg)")),
        }
    }
}

/// Fill colour of a node: leaves by tag, composites white, the Inverter grey.
fn fill(kind: &Kind) -> &'static str {
    match kind {
        Kind::Leaf(_, Tag::PostCnd) => "#c8e6c9",
        Kind::Leaf(_, Tag::PreCnd) => "#fff3c4",
        Kind::Leaf(_, Tag::Cnstr) => "#ffcdd2",
        Kind::Leaf(_, Tag::Act) => "#bbdefb",
        Kind::Leaf(_, Tag::Other(_)) => "#e0e0e0",
        Kind::Inverter => "#eeeeee",
        Kind::Sequence | Kind::Selector | Kind::Parallel => "#ffffff",
    }
}

/// Text for XML content and attribute values.
fn xml_escape(s: &str) -> String {
    let mut out = String::with_capacity(s.len());
    for c in s.chars() {
        match c {
            '&' => out.push_str("&amp;"),
            '<' => out.push_str("&lt;"),
            '>' => out.push_str("&gt;"),
            '"' => out.push_str("&quot;"),
            '\'' => out.push_str("&apos;"),
            c => out.push(c),
        }
    }
    out
}

/// Text for a DOT double-quoted string.
fn dot_escape(s: &str) -> String {
    s.replace('\\', "\\\\").replace('"', "\\\"").replace('\n', "\\n")
}

/// Font size of the SVG labels, in px; the layout assumes a monospace advance of 0.6 em.
const FONT: f64 = 12.0;
const CHAR_W: f64 = FONT * 0.6;
/// Horizontal padding inside a box, box height, gap between sibling bands, distance
/// between the tops of two levels, and the margin around the drawing.
const PAD: f64 = 8.0;
const BOX_H: f64 = 24.0;
const GAP: f64 = 12.0;
const LEVEL: f64 = 56.0;
const MARGIN: f64 = 10.0;

/// Where each node is drawn: centre x, level, box width.
struct Placement {
    x: Vec<f64>,
    level: Vec<usize>,
    width: Vec<f64>,
    /// Width of the whole drawing (without margins).
    span: f64,
}

impl Placement {
    fn of(bt: &Bt, labels: &[String]) -> Placement {
        let n = bt.nodes.len();
        let width: Vec<f64> = labels.iter().map(|l| l.chars().count() as f64 * CHAR_W + 2.0 * PAD).collect();
        // Band width of each subtree, bottom-up: nodes are in pre-order, so every child
        // has a larger index than its parent.
        let mut band = vec![0.0; n];
        for i in (0..n).rev() {
            let kids = &bt.nodes[i].children;
            let row: f64 =
                kids.iter().map(|&c| band[c as usize]).sum::<f64>() + GAP * kids.len().saturating_sub(1) as f64;
            band[i] = width[i].max(row);
        }
        let mut p = Placement { x: vec![0.0; n], level: vec![0; n], width, span: band.first().copied().unwrap_or(0.0) };
        if n > 0 {
            p.place(bt, &band, 0, 0.0, 0);
        }
        p
    }

    /// Place node `i`'s subtree in the band starting at `left`.
    fn place(&mut self, bt: &Bt, band: &[f64], i: usize, left: f64, level: usize) {
        self.level[i] = level;
        let kids = &bt.nodes[i].children;
        let row: f64 = kids.iter().map(|&c| band[c as usize]).sum::<f64>() + GAP * kids.len().saturating_sub(1) as f64;
        let mut x = left + (band[i] - row.max(0.0)) / 2.0;
        for &c in kids {
            self.place(bt, band, c as usize, x, level + 1);
            x += band[c as usize] + GAP;
        }
        let half = self.width[i] / 2.0;
        self.x[i] = match (kids.first(), kids.last()) {
            (Some(&a), Some(&b)) => {
                // Centred over the children, but inside its own band.
                ((self.x[a as usize] + self.x[b as usize]) / 2.0).clamp(left + half, left + band[i] - half)
            }
            _ => left + band[i] / 2.0,
        };
    }
}

impl Bt {
    /// The tree in `format`.
    pub fn draw(&self, format: TreeFormat) -> String {
        match format {
            TreeFormat::Text => self.render(),
            TreeFormat::Dot => self.to_dot(),
            TreeFormat::Svg => self.to_svg(),
        }
    }

    /// A Graphviz digraph: node `n<i>` is the i-th node in pre-order, labelled as in
    /// [`Bt::render`]; children keep their tick order (`ordering=out`).
    pub fn to_dot(&self) -> String {
        let mut out = String::from("digraph bt {\n  graph [ordering=out];\n  node [fontname=\"monospace\"];\n");
        for (i, node) in self.nodes.iter().enumerate() {
            let label = dot_escape(&node.kind.label());
            let style = match node.kind {
                Kind::Leaf(..) => "style=\"rounded,filled\"",
                Kind::Inverter => "style=filled",
                _ => "style=solid",
            };
            let _ =
                writeln!(out, "  n{i} [label=\"{label}\", shape=box, {style}, fillcolor=\"{}\"];", fill(&node.kind));
        }
        for (i, node) in self.nodes.iter().enumerate() {
            for c in &node.children {
                let _ = writeln!(out, "  n{i} -> n{c};");
            }
        }
        out.push_str("}\n");
        out
    }

    /// A self-contained SVG drawing (see the module documentation): one `<g>` holding a
    /// `<rect>` and a `<text>` per node, after the `<line>` edges.
    pub fn to_svg(&self) -> String {
        let labels: Vec<String> = self.nodes.iter().map(|n| n.kind.label()).collect();
        let p = Placement::of(self, &labels);
        let levels = p.level.iter().max().map_or(0, |l| l + 1);
        let w = p.span + 2.0 * MARGIN;
        let h = if levels == 0 { 0.0 } else { (levels - 1) as f64 * LEVEL + BOX_H } + 2.0 * MARGIN;
        let top = |i: usize| MARGIN + p.level[i] as f64 * LEVEL;
        let mut out = String::new();
        let _ = writeln!(
            out,
            "<svg xmlns=\"http://www.w3.org/2000/svg\" width=\"{w:.1}\" height=\"{h:.1}\" viewBox=\"0 0 {w:.1} {h:.1}\" \
             font-family=\"monospace\" font-size=\"{FONT}\" style=\"background-color:#ffffff\">"
        );
        for (i, node) in self.nodes.iter().enumerate() {
            for &c in &node.children {
                let c = c as usize;
                let _ = writeln!(
                    out,
                    "<line x1=\"{:.1}\" y1=\"{:.1}\" x2=\"{:.1}\" y2=\"{:.1}\" stroke=\"#666666\"/>",
                    MARGIN + p.x[i],
                    top(i) + BOX_H,
                    MARGIN + p.x[c],
                    top(c)
                );
            }
        }
        for (i, node) in self.nodes.iter().enumerate() {
            let (x, y, bw) = (MARGIN + p.x[i], top(i), p.width[i]);
            let rx = if matches!(node.kind, Kind::Leaf(..)) { 8 } else { 0 };
            let _ = writeln!(
                out,
                "<g><rect x=\"{:.1}\" y=\"{y:.1}\" width=\"{bw:.1}\" height=\"{BOX_H:.1}\" rx=\"{rx}\" fill=\"{}\" \
                 stroke=\"#333333\"/><text x=\"{x:.1}\" y=\"{:.1}\" text-anchor=\"middle\">{}</text></g>",
                x - bw / 2.0,
                fill(&node.kind),
                y + BOX_H / 2.0 + FONT * 0.35,
                xml_escape(&labels[i])
            );
        }
        out.push_str("</svg>\n");
        out
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::ge::{self, GeParams, Grammar};

    /// REFERENCE §4.5's worked BeTr-GEESE genome (`forge.bnf`@master): a PPA whose
    /// pre-condition is inverted.
    const GENOME: [u32; 22] = [
        1027, 25, 1038, 773, 1037, 793, 953, 372, 1146, 1579, 473, 816, 219, 562, 786, 606, 897, 1539, 1964, 164, 1807,
        896,
    ];

    fn worked_tree() -> Bt {
        let g = Grammar::parse(ge::testdata::FORGE).expect("grammar");
        let ind = ge::evaluate(&g, GENOME.to_vec(), &GeParams::default());
        let ph = ind.phenotype.expect("valid genome");
        Bt::from_pnode(&ge::parse_phenotype(&ph).expect("parses")).expect("builds")
    }

    #[test]
    fn text_is_the_indented_rendering() {
        let bt = worked_tree();
        let text = "Selector\n  Selector\n    Sequence\n      IsCarrying[Food] (PostCnd)\n    Sequence\n      Sequence\n        Inverter\n          IsVisitedBefore[Sites] (PreCnd)\n        MoveAway[Hub] (Act)\n";
        assert_eq!(bt.render(), text);
        assert_eq!(bt.draw(TreeFormat::Text), text);
    }

    #[test]
    fn dot_of_the_worked_genome() {
        let expected = r##"digraph bt {
  graph [ordering=out];
  node [fontname="monospace"];
  n0 [label="Selector", shape=box, style=solid, fillcolor="#ffffff"];
  n1 [label="Selector", shape=box, style=solid, fillcolor="#ffffff"];
  n2 [label="Sequence", shape=box, style=solid, fillcolor="#ffffff"];
  n3 [label="IsCarrying[Food] (PostCnd)", shape=box, style="rounded,filled", fillcolor="#c8e6c9"];
  n4 [label="Sequence", shape=box, style=solid, fillcolor="#ffffff"];
  n5 [label="Sequence", shape=box, style=solid, fillcolor="#ffffff"];
  n6 [label="Inverter", shape=box, style=filled, fillcolor="#eeeeee"];
  n7 [label="IsVisitedBefore[Sites] (PreCnd)", shape=box, style="rounded,filled", fillcolor="#fff3c4"];
  n8 [label="MoveAway[Hub] (Act)", shape=box, style="rounded,filled", fillcolor="#bbdefb"];
  n0 -> n1;
  n1 -> n2;
  n1 -> n4;
  n2 -> n3;
  n4 -> n5;
  n5 -> n6;
  n5 -> n8;
  n6 -> n7;
}
"##;
        assert_eq!(worked_tree().draw(TreeFormat::Dot), expected);
        assert_eq!(dot_escape(r#"a"b\c"#), r#"a\"b\\c"#);
    }

    /// Checks that `s` is well-formed XML of the subset the SVG writer uses (elements,
    /// quoted attributes, text, the five predefined entities) and returns the element
    /// names in document order.
    fn xml_elements(s: &str) -> Result<Vec<String>, String> {
        let mut open: Vec<String> = Vec::new();
        let mut names = Vec::new();
        let mut rest = s;
        let check_text = |t: &str| -> Result<(), String> {
            let mut parts = t.split('&');
            parts.next();
            for p in parts {
                if !["amp;", "lt;", "gt;", "quot;", "apos;"].iter().any(|e| p.starts_with(e)) {
                    return Err(format!("bare & in {t:?}"));
                }
            }
            if t.contains('>') {
                return Err(format!("bare > in {t:?}"));
            }
            Ok(())
        };
        while let Some(lt) = rest.find('<') {
            check_text(&rest[..lt])?;
            let gt = rest[lt..].find('>').ok_or("unterminated tag")? + lt;
            let tag = &rest[lt + 1..gt];
            rest = &rest[gt + 1..];
            if let Some(name) = tag.strip_prefix('/') {
                if open.pop().as_deref() != Some(name) {
                    return Err(format!("</{name}> closes nothing open"));
                }
                continue;
            }
            let (body, empty) = tag.strip_suffix('/').map_or((tag, false), |b| (b, true));
            let name = body.split_whitespace().next().ok_or("empty tag")?.to_string();
            if body.starts_with(char::is_whitespace) || !name.chars().all(|c| c.is_ascii_alphanumeric() || c == '-') {
                return Err(format!("bad element name in <{tag}>"));
            }
            // Attributes: name="value" pairs, values without < or a bare &.
            let mut attrs = body[name.len()..].trim();
            while !attrs.is_empty() {
                let eq = attrs.find("=\"").ok_or(format!("attribute without a quoted value in <{tag}>"))?;
                let end = attrs[eq + 2..].find('"').ok_or("unterminated attribute value")? + eq + 2;
                let value = &attrs[eq + 2..end];
                if value.contains('<') {
                    return Err(format!("< in attribute value {value:?}"));
                }
                check_text(value)?;
                attrs = attrs[end + 1..].trim_start();
            }
            names.push(name.clone());
            if !empty {
                open.push(name);
            }
        }
        check_text(rest)?;
        if !rest.trim().is_empty() || !open.is_empty() {
            return Err(format!("unclosed elements {open:?} or trailing text"));
        }
        Ok(names)
    }

    #[test]
    fn svg_is_well_formed_with_one_group_box_and_label_per_node() {
        let bt = worked_tree();
        let svg = bt.draw(TreeFormat::Svg);
        let names = xml_elements(&svg).unwrap_or_else(|e| panic!("{e}\n{svg}"));
        let count = |n: &str| names.iter().filter(|x| *x == n).count();
        assert_eq!(names[0], "svg");
        assert_eq!((count("g"), count("rect"), count("text")), (9, 9, 9));
        assert_eq!(count("line"), 8, "one edge per non-root node");
        assert!(svg.contains(">IsVisitedBefore[Sites] (PreCnd)</text>"), "{svg}");
        // Leaves share one row per level and never overlap their neighbours: the five
        // nodes of the deepest levels are left to right in tick order.
        let xs: Vec<f64> =
            svg.lines().filter_map(|l| l.split("<text x=\"").nth(1)?.split('"').next()?.parse().ok()).collect();
        assert_eq!(xs.len(), 9);
        assert!(xs[3] < xs[7] && xs[7] < xs[8], "leaves left to right: {xs:?}");
        assert!((xs[0] - xs[1]).abs() < 1e-9, "a single child sits under its parent");
    }

    #[test]
    fn svg_and_dot_escape_labels() {
        // A tag is the only free text a phenotype puts into a label; `<` cannot occur in
        // one, `&` and `"` can.
        let p = ge::parse_phenotype(r#"[Sequence][a&b"c]Explore[/a&b"c][/Sequence]"#).expect("parses");
        let bt = Bt::from_pnode(&p).expect("builds");
        let svg = bt.to_svg();
        xml_elements(&svg).unwrap_or_else(|e| panic!("{e}\n{svg}"));
        assert!(svg.contains("Explore (a&amp;b&quot;c)"), "{svg}");
        assert!(bt.to_dot().contains(r#"label="Explore (a&b\"c)""#), "{}", bt.to_dot());
        assert_eq!(xml_escape("<a & 'b'>\""), "&lt;a &amp; &apos;b&apos;&gt;&quot;");
        assert!(xml_elements("<svg><g>a < b</g></svg>").is_err(), "the checker sees a bare <");
        assert!(xml_elements("<svg>a & b</svg>").is_err(), "the checker sees a bare &");
    }

    #[test]
    fn formats_parse_by_name() {
        assert_eq!("svg".parse::<TreeFormat>(), Ok(TreeFormat::Svg));
        assert_eq!("dot".parse::<TreeFormat>(), Ok(TreeFormat::Dot));
        assert_eq!("text".parse::<TreeFormat>(), Ok(TreeFormat::Text));
        let e = "png".parse::<TreeFormat>().unwrap_err();
        assert!(e.contains("'png'") && e.contains("text, dot or svg"), "{e}");
    }
}
