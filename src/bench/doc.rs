//! A tiny document model for the bench report: headings, paragraphs, tables, images and code,
//! written once and rendered both as Markdown (`REPORT.md`, images as side files) and as
//! self-contained HTML (`report.html`, images inline as base64).

use std::collections::BTreeMap;

use base64::Engine;

pub enum Block {
    Heading(u8, String),
    Para(String),
    Table(Vec<String>, Vec<Vec<String>>),
    /// A PNG written beside the report, by file name.
    Image(String, String),
    Code(String),
}

#[derive(Default)]
pub struct Doc {
    pub blocks: Vec<Block>,
}

impl Doc {
    pub fn h(&mut self, level: u8, text: impl Into<String>) {
        self.blocks.push(Block::Heading(level, text.into()));
    }
    pub fn p(&mut self, text: impl Into<String>) {
        self.blocks.push(Block::Para(text.into()));
    }
    pub fn table(&mut self, header: &[&str], rows: Vec<Vec<String>>) {
        self.blocks.push(Block::Table(
            header.iter().map(|s| s.to_string()).collect(),
            rows,
        ));
    }
    pub fn image(&mut self, file: impl Into<String>, alt: impl Into<String>) {
        self.blocks.push(Block::Image(file.into(), alt.into()));
    }
    pub fn code(&mut self, text: impl Into<String>) {
        self.blocks.push(Block::Code(text.into()));
    }

    pub fn markdown(&self) -> String {
        let mut out = String::new();
        for b in &self.blocks {
            match b {
                Block::Heading(l, t) => {
                    out.push_str(&format!("{} {t}\n\n", "#".repeat(*l as usize)))
                }
                Block::Para(t) => out.push_str(&format!("{t}\n\n")),
                Block::Table(h, rows) => {
                    let cell = |s: &String| s.replace('|', "\\|");
                    out.push_str(&format!(
                        "| {} |\n|{}\n",
                        h.iter().map(cell).collect::<Vec<_>>().join(" | "),
                        " --- |".repeat(h.len())
                    ));
                    for r in rows {
                        out.push_str(&format!(
                            "| {} |\n",
                            r.iter().map(cell).collect::<Vec<_>>().join(" | ")
                        ));
                    }
                    out.push('\n');
                }
                Block::Image(f, alt) => out.push_str(&format!("![{alt}]({f})\n\n")),
                Block::Code(t) => out.push_str(&format!("```\n{t}\n```\n\n")),
            }
        }
        out
    }

    /// Self-contained HTML; `images` holds the PNG bytes of every `Image` block by file name.
    pub fn html(&self, title: &str, images: &BTreeMap<String, Vec<u8>>) -> String {
        let mut out = format!(
            "<!doctype html>\n<html><head><meta charset=\"utf-8\"><title>{}</title><style>\
             body{{font-family:sans-serif;max-width:1400px;margin:2em auto;padding:0 1em;color:#222}}\
             table{{border-collapse:collapse;margin:1em 0}}td,th{{border:1px solid #ccc;padding:3px 8px;text-align:left}}\
             th{{background:#f3f3f3}}img{{max-width:100%}}pre{{background:#f6f6f6;padding:1em;overflow:auto}}\
             </style></head><body>\n",
            esc(title)
        );
        for b in &self.blocks {
            match b {
                Block::Heading(l, t) => out.push_str(&format!("<h{l}>{}</h{l}>\n", inline(t))),
                Block::Para(t) => out.push_str(&format!("<p>{}</p>\n", inline(t))),
                Block::Table(h, rows) => {
                    out.push_str("<table><tr>");
                    for c in h {
                        out.push_str(&format!("<th>{}</th>", inline(c)));
                    }
                    out.push_str("</tr>\n");
                    for r in rows {
                        out.push_str("<tr>");
                        for c in r {
                            out.push_str(&format!("<td>{}</td>", inline(c)));
                        }
                        out.push_str("</tr>\n");
                    }
                    out.push_str("</table>\n");
                }
                Block::Image(f, alt) => match images.get(f) {
                    Some(bytes) => out.push_str(&format!(
                        "<p><img alt=\"{}\" src=\"data:image/png;base64,{}\"></p>\n",
                        esc(alt),
                        base64::engine::general_purpose::STANDARD.encode(bytes)
                    )),
                    None => out.push_str(&format!(
                        "<p><img alt=\"{}\" src=\"{}\"></p>\n",
                        esc(alt),
                        esc(f)
                    )),
                },
                Block::Code(t) => out.push_str(&format!("<pre>{}</pre>\n", esc(t))),
            }
        }
        out.push_str("</body></html>\n");
        out
    }
}

fn esc(s: &str) -> String {
    s.replace('&', "&amp;")
        .replace('<', "&lt;")
        .replace('>', "&gt;")
        .replace('"', "&quot;")
}

/// Escapes text and turns Markdown's `code` and **bold** spans into HTML.
fn inline(s: &str) -> String {
    let mut out = String::new();
    for (i, part) in esc(s).split('`').enumerate() {
        if i % 2 == 1 {
            out.push_str(&format!("<code>{part}</code>"));
        } else {
            for (j, q) in part.split("**").enumerate() {
                if j % 2 == 1 {
                    out.push_str(&format!("<b>{q}</b>"));
                } else {
                    out.push_str(q);
                }
            }
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn renders_markdown_and_html() {
        let mut d = Doc::default();
        d.h(1, "Title");
        d.p("a `b` **c** <d>");
        d.table(&["x", "y"], vec![vec!["1".into(), "a|b".into()]]);
        d.image("p.png", "plot");
        let md = d.markdown();
        assert!(
            md.contains("# Title\n")
                && md.contains("| 1 | a\\|b |")
                && md.contains("![plot](p.png)")
        );
        let html = d.html("t", &BTreeMap::from([("p.png".to_string(), vec![1, 2, 3])]));
        assert!(html.contains("<code>b</code> <b>c</b> &lt;d&gt;"), "{html}");
        assert!(html.contains("data:image/png;base64,AQID"));
    }
}
