-- object_type_words: words that name what an object is (a kind of thing or a coarse shape noun).
-- A caption that names none of them says nothing a text query can match on besides colour and size.
-- Matched case-insensitively as whole words, plurals allowed; "box-shaped" matches "box".
CREATE OR REPLACE VIEW object_type_words AS
SELECT CAST(word AS VARCHAR) AS word
FROM (
    VALUES
        -- containers and packaging
        ('bottle'), ('box'), ('can'), ('tin'), ('jar'), ('jug'), ('pitcher'), ('cup'), ('mug'), ('bowl'),
        ('plate'), ('dish'), ('pot'), ('pan'), ('container'), ('package'), ('packet'), ('carton'),
        ('bag'), ('tube'), ('lid'), ('cap'), ('canister'), ('bucket'), ('basket'), ('case'),
        -- tools and utensils
        ('tool'), ('drill'), ('hammer'), ('screwdriver'), ('wrench'), ('spanner'), ('clamp'),
        ('scissors'), ('knife'), ('fork'), ('spoon'), ('spatula'), ('marker'), ('pen'), ('pencil'),
        ('brush'), ('sponge'), ('key'), ('lock'), ('chain'), ('rope'), ('bolt'), ('nut'), ('screw'),
        -- food and everyday objects
        ('fruit'), ('banana'), ('apple'), ('lemon'), ('peach'), ('pear'), ('plum'), ('strawberry'),
        ('cracker'), ('toy'), ('figure'), ('figurine'), ('block'), ('brick'), ('ball'), ('cube'),
        ('phone'), ('remote'), ('camera'), ('lamp'), ('shoe'), ('glass'), ('vase'), ('book'),
        ('chair'), ('table'), ('cable'), ('plug'), ('battery'),
        -- coarse shape nouns
        ('cylinder'), ('sphere'), ('cone'), ('disk'), ('disc'), ('ring'), ('rod'), ('bar'), ('plank'),
        ('board'), ('sheet'), ('slab'), ('pyramid'), ('prism')
) AS t(word);

COMMENT ON VIEW object_type_words IS 'words that name a kind of object or a coarse shape, looked for by the caption audits';
COMMENT ON COLUMN object_type_words.word IS 'lower-case object type word, matched as a whole word';
