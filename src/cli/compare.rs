//! `sylva compare`: the error of linear images against a reference.

use super::*;

#[derive(Args, Debug)]
pub(crate) struct CompareArgs {
    /// The reference image.
    #[arg(long, short, value_name = "FILE")]
    reference: PathBuf,
    /// Images to compare with it.
    #[arg(required = true, value_name = "IMAGE")]
    images: Vec<PathBuf>,
}

/// The pixels of a linear image, row-major.
fn pixels(map: &EnvironmentMap) -> Vec<Vec3> {
    (0..map.height())
        .flat_map(|y| (0..map.width()).map(move |x| map.texel(x, y)))
        .collect()
}

/// Runs `sylva compare`.
pub(crate) fn run(args: CompareArgs) -> Result<()> {
    let reference = load_linear_image(&args.reference)?;
    let (width, height) = (reference.width(), reference.height());
    let reference = pixels(&reference);
    println!("{:<40} {:>12} {:>12}", "image", "rmse", "relmse");
    for path in &args.images {
        let image = load_linear_image(path)?;
        let (w, h) = (image.width(), image.height());
        let image = pixels(&image);
        if (w, h) != (width, height) {
            bail!(
                "{}: the image is {w}x{h} but the reference {} is {width}x{height}",
                path.display(),
                args.reference.display()
            );
        }
        let error = sylva::engine::metrics::image_error(&reference, &image)
            .expect("sizes were checked and are non-zero");
        println!(
            "{:<40} {:>12.6} {:>12.6}",
            path.display(),
            error.rmse,
            error.relmse
        );
    }
    Ok(())
}
