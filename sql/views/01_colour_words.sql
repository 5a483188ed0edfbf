-- colour_words: the colour names the caption audits look for.
-- Matched case-insensitively as whole words, plurals allowed ("reds" matches "red"). Edit the list here;
-- every audit and view that needs it reads it from this view.
CREATE OR REPLACE VIEW colour_words AS
SELECT CAST(word AS VARCHAR) AS word
FROM (
    VALUES
        ('black'), ('white'), ('gray'), ('grey'), ('silver'), ('gold'), ('golden'), ('red'), ('orange'),
        ('yellow'), ('green'), ('blue'), ('purple'), ('violet'), ('pink'), ('brown'), ('beige'), ('tan'),
        ('cream'), ('maroon'), ('navy'), ('teal'), ('cyan'), ('magenta'), ('turquoise'), ('olive'),
        ('bronze'), ('copper'), ('ivory'), ('khaki'), ('lavender'), ('crimson')
) AS t(word);

COMMENT ON VIEW colour_words IS 'colour names looked for by the caption audits';
COMMENT ON COLUMN colour_words.word IS 'lower-case colour word, matched as a whole word';
