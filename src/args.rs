//! Argument parsers shared by the subcommands (`--size WxH`, `--pixel X,Y`).

pub fn parse_size(s: &str) -> Result<(u32, u32), String> {
    let (w, h) = s.split_once(['x', 'X']).ok_or("expected WxH, e.g. 64x48")?;
    let w: u32 = w.trim().parse().map_err(|_| format!("bad width {w:?}: expected a positive integer"))?;
    let h: u32 = h.trim().parse().map_err(|_| format!("bad height {h:?}: expected a positive integer"))?;
    if w == 0 || h == 0 {
        return Err("width and height must be positive".into());
    }
    Ok((w, h))
}

pub fn parse_pixel(s: &str) -> Result<(u32, u32), String> {
    let (x, y) = s.split_once(',').ok_or("expected X,Y, e.g. 10,20")?;
    let x = x.trim().parse().map_err(|_| format!("bad x {x:?}: expected a non-negative integer"))?;
    let y = y.trim().parse().map_err(|_| format!("bad y {y:?}: expected a non-negative integer"))?;
    Ok((x, y))
}

/// `--tracer`: path (or cpu), whitted or gpu.
pub fn parse_tracer(s: &str) -> Result<renderers::TracerChoice, String> {
    s.parse().map_err(|e: renderers::Error| e.to_string())
}
